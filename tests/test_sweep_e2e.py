"""``sweep`` on Debian's real, unmodified C++ nodes (image_publisher + opencv_apps'
hough_circles, fixtures/app/app.launch), then ``init`` -> ``characterise`` -> ``fit`` ->
``solve`` -> ``deploy`` (which validates) with no file written by hand.

Checked against independent sources: the nodes and the subscription of the drafted system
against the launch file's own XML; every recorded rate against Debian's rosbag API (under
/usr/bin/python3) and against the rate the run asked the camera for. Ctrl-C in the middle of
a run, and a node killed during a recording, leave every finished run, a manifest that lists
exactly those, and nothing running: no process carrying the run's tag, nothing on its
master's port, no cgroup.
"""

from __future__ import annotations

import functools
import json
import os
import re
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml

from perfros_bag.characterisation.manifest import load_manifest
from perfros_bag.cpu.trace import read_cpu_trace
from perfros_bag.rosrun.cgroups import leftover_groups
from perfros_bag.rosrun.processes import RUN_ENV, leftover_processes
from tests.conftest import FIXTURES, communicate_or_stacks
from tests.test_casestudy_e2e import (
    BAG_RATES,
    ROS_PY,
    _cgroups_work,  # the case study's independent checks
    _processes_on,
)

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).with_name("perfros-bag")
APP = FIXTURES / "app" / "app.launch"


def _require_ros() -> None:
    for tool in ("/usr/bin/roscore", "/usr/bin/roslaunch", "/usr/bin/rosbag", ROS_PY,
                 "/usr/lib/image_publisher/image_publisher", "/usr/lib/opencv_apps/hough_circles",
                 "/usr/share/nodelet/package.xml"):
        assert os.path.exists(tool), f"{tool} missing: make setup-debs (see the Makefile's DEBS)"


def _space(path: Path, **top: Any) -> Path:
    doc = {"duration_s": 4, "settle_s": 1, "repeats": 1, "design": "grid", "startup_timeout_s": 30,
           "vary": [{"node": "camera", "parameter": {"name": "publish_rate", "unit": "Hz"},
                     "arg": "camera_rate", "values": [5, 10]},
                    {"node": "detector", "parameter": {"name": "canny_threshold"},
                     "arg": "canny_threshold", "values": [100, 200]}]}
    doc.update(top)
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _cli(*args: str, timeout: float = 120, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN), *args], capture_output=True, text=True, timeout=timeout, cwd=cwd)


def _ours(out: Path) -> list[psutil.Process]:
    """Live processes a sweep into ``out`` started: tagged, with their ROS_HOME under ``out``."""
    found = []
    for p in psutil.process_iter(["pid"]):
        try:
            env = p.environ()
            alive = p.status() != psutil.STATUS_ZOMBIE
        except (psutil.Error, OSError):
            continue
        if alive and RUN_ENV in env and env.get("ROS_HOME", "").startswith(str(out)):
            found.append(p)
    return found


def _nothing_left(out: Path, tags: set[str], ports: set[int]) -> None:
    deadline = time.monotonic() + 5
    while (_ours(out) or any(_processes_on(p) for p in ports)) and time.monotonic() < deadline:
        time.sleep(0.2)
    assert _ours(out) == []
    for tag in tags:
        assert leftover_processes(tag) == [], tag
        assert leftover_groups(run_id=tag) == [], tag
    for port in ports:
        assert _processes_on(port) == [], port


def _launch_nodes(launch: Path) -> dict[str, dict[str, str]]:
    """The launch file's nodes by ROS name, with their remappings, read from its XML."""
    root = ET.parse(launch).getroot()
    return {"/" + n.get("name", ""): {r.get("from", ""): r.get("to", "") for r in n.iter("remap")}
            for n in root.iter("node")}


@functools.cache
def _bag_rates(bag: Path) -> dict[str, float]:
    """Per-topic rates by Debian's rosbag API (each bag read once)."""
    done = subprocess.run([ROS_PY, "-c", BAG_RATES, str(bag)], capture_output=True, text=True, timeout=60,
                          check=True, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    rates: dict[str, float] = json.loads(done.stdout)
    return rates


#: The README's example ("Starting from your own launch file"), its runs shortened to 4 s.
SPACE = FIXTURES / "app" / "space.yaml"
SHORT = ("--duration", "4")


def sweep_once(factory: pytest.TempPathFactory, name: str,
               **top: Any) -> tuple[Path, Path, subprocess.CompletedProcess[str]]:
    """``sweep`` of fixtures/app into a new folder with ``_space(**top)``: (folder, out, result)."""
    _require_ros()
    d = factory.mktemp(name)
    out = d / "rec"
    done = _cli("sweep", str(APP), "--space", str(_space(d / "space.yaml", **top)), "--out", str(out), timeout=150)
    return d, out, done


def succeeded(out: Path, done: subprocess.CompletedProcess[str]) -> None:
    """A sweep that ended well: exit 0, no traceback, nothing of it left running."""
    assert done.returncode == 0, done.stderr
    assert "Traceback" not in done.stderr
    _nothing_left(out, set(), set())


def drafted(d: Path, out: Path, done: subprocess.CompletedProcess[str]) -> tuple[Path, dict[str, Any]]:
    """``init`` of a sweep that succeeded into ``d/system.yaml``: the file and its document."""
    assert done.returncode == 0, done.stderr
    system = d / "system.yaml"
    step = _cli("init", str(out), "--out", str(system))
    assert step.returncode == 0, step.stderr
    doc: dict[str, Any] = yaml.safe_load(system.read_text())
    return system, doc


def kill_mid_recording(proc: subprocess.Popen[str], out: Path, program: str,
                       runs_before: int = 0) -> tuple[str, set[str], set[int]]:
    """Kill the one process of a running sweep into ``out`` whose command line names
    ``program``, once ``runs_before`` runs are recorded and the next one's recorder runs: the
    sweep ends with exit 2 and one line, returned with the run's tags and master ports."""
    try:
        _wait(lambda: len(_recorded(out)) == runs_before, proc, 60, f"{runs_before} run(s)")
        _wait(lambda: bool(_running(out, "__name:=perfros_record")), proc, 90, "the recording")
        tags, ports = _tags_and_ports(out)
        victims = _running(out, program)
        assert len(victims) == 1
        victims[0].kill()
        _, stderr = communicate_or_stacks(proc, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 2, stderr
    lines = [x for x in stderr.splitlines() if x.strip()]
    assert len(lines) == 1, stderr
    return lines[0], tags, ports


def interrupt(proc: subprocess.Popen[str]) -> str:
    """Ctrl-C a running ``sweep``: it ends with 130 and says so, no traceback; its stderr."""
    proc.send_signal(signal.SIGINT)
    _, stderr = communicate_or_stacks(proc, 60)
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr and "interrupted" in stderr
    return stderr


@pytest.fixture(scope="module")
def swept(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, subprocess.CompletedProcess[str]]:
    """Step 1 of the README, in a folder of its own: ``sweep fixtures/app/app.launch --space
    fixtures/app/space.yaml --out runs/`` (4 s runs)."""
    _require_ros()
    d = tmp_path_factory.mktemp("sweep")
    out = d / "runs"
    done = _cli("sweep", str(APP), "--space", str(SPACE), "--out", "runs/", *SHORT, timeout=150, cwd=d)
    return d, out, done


def test_sweep_records_every_setting_and_leaves_nothing(swept: tuple[Path, Path, Any]) -> None:
    d, out, done = swept
    succeeded(out, done)
    manifest = load_manifest(out / "manifest.yaml")
    settings = sorted((e.settings["camera"], e.settings["detector"]) for e in manifest.recordings)
    assert settings == [(5, 100), (5, 200), (10, 100), (10, 200)]
    for e in manifest.recordings:
        assert e.path.is_file() and e.cpu is not None and e.cpu.is_file()
        # the machine's speed as record-cpu measured it, in the trace and in the manifest
        assert e.speed_factor is not None and e.speed_factor > 0
        assert read_cpu_trace(e.cpu).speed_factor == pytest.approx(e.speed_factor, rel=1e-3)
    assert not (out / ".sweep").exists()

    # graph.yaml: the launch file's nodes with their PIDs and programs, and its remapping
    graph = yaml.safe_load((out / "graph.yaml").read_text())
    assert graph["format"] == "perfros-bag/graph@1"
    launched = {n["name"]: n for n in graph["nodes"] if n["launched"]}
    declared = _launch_nodes(APP)
    assert set(launched) == set(declared)
    assert launched["/camera"]["executable"].endswith("image_publisher")
    assert launched["/detector"]["executable"].endswith("hough_circles")
    assert all(isinstance(n["pid"], int) and n["pid"] > 0 for n in launched.values())
    topics = {t["name"]: t for t in graph["topics"]}
    image = "/" + declared["/detector"]["image"]  # the detector's input, remapped in the launch file
    assert topics[image]["publishers"] == ["/camera"] and topics[image]["subscribers"] == ["/detector"]
    assert topics[image]["type"] == "sensor_msgs/Image"

    # rates: Debian's rosbag reader against what each run asked the camera for
    for e in manifest.recordings:
        rates = _bag_rates(e.path)
        assert abs(rates[image] / e.settings["camera"] - 1) < 0.1, (e.name, rates[image])
        assert rates["/detector/circles"] > 0  # the detector worked on the camera's images

    # the CPU traces name the ROS nodes, and only them
    for e in manifest.recordings:
        assert e.cpu is not None
        rows = [line.split(",") for line in e.cpu.read_text().splitlines() if line and not line.startswith("#")]
        assert {r[2] for r in rows[1:]} == set(declared), e.cpu

    # again: every run is already there
    again = _cli("sweep", str(APP), "--space", str(SPACE), "--out", str(out), *SHORT)
    assert again.returncode == 0, again.stderr
    assert "0 run(s) recorded, 4 already there" in again.stderr


def test_the_readme_example_holds_within_2_5_percent(swept: tuple[Path, Path, Any]) -> None:
    """The README's steps as written ("Starting from your own launch file"; 4 s runs), with no
    file written by hand: the detector is drafted as driven by the camera's images, the plan
    expects it at the camera's planned rate, and the deployment deviates by at most 2.5 %."""
    d, out, done = swept
    assert done.returncode == 0, done.stderr
    steps = [("init", "runs/", "--out", "system.yaml"),
             ("characterise", "runs/", "--system", "system.yaml", "--out", "characterisation.csv", "--latency"),
             ("fit", "system.yaml", "characterisation.csv", "--out", "model.json"),
             ("solve", "model.json", "--problem", "1", "--method", "exact", "--out", "plan.json")]
    for args in steps:
        step = _cli(*args, cwd=d)
        assert step.returncode == 0, (args[0], step.stderr)
        assert "Traceback" not in step.stderr
    system = d / "system.yaml"
    doc = yaml.safe_load(system.read_text())
    declared = _launch_nodes(APP)
    assert {n["name"] for n in doc["nodes"]} == {n.lstrip("/") for n in declared}
    image = "/" + declared["/detector"]["image"]
    assert doc["edges"] == [{"from": "camera", "to": "detector", "topic": image}]
    nodes = {n["name"]: n for n in doc["nodes"]}
    assert nodes["camera"]["parameter"] == {"name": "publish_rate", "unit": "Hz"}
    assert "input" not in nodes["camera"] and nodes["detector"]["input"] == image  # the source, the driven
    assert [s["value"] for s in nodes["camera"]["settings"]] == [5, 10]
    assert [s["value"] for s in nodes["detector"]["settings"]] == [100, 200]
    assert all({"cpu", "cpu_per_hz", "out_per_in", "bytes_per_msg"} <= set(s) for s in nodes["detector"]["settings"])
    assert image in nodes["camera"]["topics"] and "/rosout" not in nodes["camera"]["topics"]
    manifest = load_manifest(out / "manifest.yaml")
    assert {e.units_per_core for e in manifest.recordings} == {100}  # the measurement's own scale
    assert doc["computers"][0]["capacity"] == 100 * int(
        next(line for line in manifest.recordings[0].cpu.read_text().splitlines()  # type: ignore[union-attr]
             if line.startswith("# logical_cpus=")).split("=")[1])
    # the drafted camera rates are the recorded ones, and the detector's output followed them
    # one for one (Debian's reader, per run)
    for s in nodes["camera"]["settings"]:
        bags = [e.path for e in manifest.recordings if e.settings["camera"] == s["value"]]
        expected = sum(_bag_rates(b)[image] for b in bags) / len(bags)
        assert abs(s["topics"][image]["frequency_hz"] / expected - 1) < 0.01, (s, expected)
    for e in manifest.recordings:
        rates = _bag_rates(e.path)
        assert abs(rates["/detector/circles"] / rates[image] - 1) < 0.05, (e.name, rates)
    for s in nodes["detector"]["settings"]:
        assert abs(s["out_per_in"] - 1) < 0.05, s
    assert "REPLACE" in system.read_text()

    # the data flow's chain, drafted without a budget, predicted by the plan (the README's example)
    assert doc["chains"] == [{"name": "detector", "topics": [image, nodes["detector"]["topics"][0]]}]
    solved = json.loads((d / "plan.json").read_text())
    assert solved["status"] in ("optimal", "feasible") and set(solved["nodes"]) == {"camera", "detector"}
    assert solved["chains"][0]["predicted_ms"]["p50"] > 0
    camera_plan, detector_plan = solved["nodes"]["camera"], solved["nodes"]["detector"]
    camera_hz = camera_plan["topics"][image]["frequency_hz"]
    assert detector_plan["input"] == image and detector_plan["input_hz"] == pytest.approx(camera_hz)
    for topic, rate in detector_plan["topics"].items():  # expected at the camera's planned rate
        assert abs(rate["frequency_hz"] / camera_hz - 1) < 0.05, (topic, rate, camera_hz)
    assert abs(camera_hz / camera_plan["value"] - 1) < 0.05
    step = _cli("solve", "system.yaml", "--problem", "1", "--method", "greedy", "--out", "plan2.json", cwd=d)
    assert step.returncode == 0, step.stderr

    # step 4: deploy the plan on this machine (its computer a cgroup when cgroups work here), validate it
    step = _cli("deploy", "plan.json", str(APP), "--space", str(SPACE), "--out", "deployed/", *SHORT, cwd=d)
    run = d / "deployed"
    assert "Traceback" not in step.stderr
    validation = json.loads((run / "validation.json").read_text())
    deviation = validation["overall"]["deviation_pct"]
    print(f"README example: deploy deviation {deviation:.2f} %")  # the figure, for the record (pytest -s)
    assert deviation <= 2.5, step.stdout
    assert step.returncode == 0, step.stderr
    record = json.loads((run / "deploy.json").read_text())
    _nothing_left(run, {record["run_id"]}, set())
    assert record["leftover_cgroups"] == []
    assert (record["cpu_cap"]["mode"] != "uncapped") == _cgroups_work()
    # the plan's value, made whole where space.yaml's values are all whole numbers (the fit's
    # inverse gives e.g. 9.999999999999995 for 10)
    assert record["values"] == {n: int(round(solved["nodes"][n]["value"])) for n in ("camera", "detector")}
    assert {n: v["computer"] for n, v in record["nodes"].items()} == {
        f"/{n}": v["computer"] for n, v in solved["nodes"].items()}
    rates = _bag_rates(run / "run.bag")
    assert abs(rates[image] / camera_plan["value"] - 1) < 0.1  # the camera ran at the planned rate
    assert abs(rates["/detector/circles"] / rates[image] - 1) < 0.05  # and the detector with it
    camera = next(n for n in validation["nodes"] if n["node"] == "camera")
    checked = next(t for t in camera["topics"] if t["topic"] == image)
    assert abs(checked["f_measured"] / rates[image] - 1) < 0.01


def test_init_without_graph_yaml_takes_the_nodes_from_the_recordings(swept: tuple[Path, Path, Any],
                                                                      tmp_path: Path) -> None:
    _d, out, done = swept
    assert done.returncode == 0, done.stderr
    bare = tmp_path / "rec"
    bare.mkdir()
    for f in out.iterdir():
        if f.name != "graph.yaml":
            (bare / f.name).symlink_to(f)
    system = tmp_path / "system.yaml"
    drafted = _cli("init", str(bare), "--out", str(system))
    assert drafted.returncode == 0, drafted.stderr
    doc = yaml.safe_load(system.read_text())
    assert {n["name"] for n in doc["nodes"]} == {n.lstrip("/") for n in _launch_nodes(APP)}
    assert "edges" not in doc and "no graph.yaml: no edges" in system.read_text()
    step = _cli("solve", str(system), "--problem", "1", "--method", "greedy", "--out", str(tmp_path / "plan.json"))
    assert step.returncode == 0, step.stderr


def _wait(cond: Any, proc: subprocess.Popen[str], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        assert proc.poll() is None, f"sweep ended before {what}: {proc.communicate()[1]}"
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        time.sleep(0.1)


def _tags_and_ports(out: Path) -> tuple[set[str], set[int]]:
    tags, ports = set(), set()
    for p in _ours(out):
        try:
            env = p.environ()
        except (psutil.Error, OSError):
            continue
        tags.add(env[RUN_ENV])
        if "ROS_MASTER_URI" in env:
            ports.add(int(env["ROS_MASTER_URI"].rstrip("/").rsplit(":", 1)[1]))
    return tags, ports


def _running(out: Path, program: str) -> list[psutil.Process]:
    found = []
    for p in _ours(out):
        try:
            if any(program in a for a in p.cmdline()):
                found.append(p)
        except psutil.Error:
            continue
    return found


def _recorded(out: Path) -> list[str]:
    path = out / "manifest.yaml"
    return [e.name for e in load_manifest(path).recordings] if path.exists() else []


def _one_line_then_consistent(out: Path, first: list[str]) -> None:
    manifest = load_manifest(out / "manifest.yaml")
    assert [e.name for e in manifest.recordings] == first
    for e in manifest.recordings:
        assert _bag_rates(e.path), e.path  # Debian's reader opens it: a finished bag
    assert sorted(p.name for p in out.glob("*.bag")) == first


def test_ctrl_c_mid_run_keeps_finished_runs_and_leaves_nothing(tmp_path: Path) -> None:
    _require_ros()
    out = tmp_path / "rec"
    # 8 s runs: the Ctrl-C must land inside the second run even when a loaded machine takes
    # seconds between seeing its nodes and sending it (CI dry run 2026-11-28 17:07: with 3 s
    # runs the sweep had finished all three before the signal came)
    space = _space(tmp_path / "space.yaml", duration_s=8, settle_s=0,
                   vary=[{"node": "camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate",
                          "values": [5, 10, 20]}])
    proc = subprocess.Popen([str(BIN), "sweep", str(APP), "--space", str(space), "--out", str(out)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        _wait(lambda: len(_recorded(out)) == 1, proc, 60, "the first run")
        _wait(lambda: bool(_running(out, "hough_circles")), proc, 30, "the second run's nodes")
        tags, ports = _tags_and_ports(out)
        assert len(tags) == 1 and len(ports) == 1
        interrupt(proc)
    finally:
        if proc.poll() is None:
            proc.kill()
    _nothing_left(out, tags, ports)
    _one_line_then_consistent(out, ["camera-publish_rate-5.bag"])
    assert not any((out / ".sweep").glob("*")), "the interrupted run's work folder is removed"


def test_a_node_dying_mid_run_is_one_line_and_leaves_nothing(tmp_path: Path) -> None:
    _require_ros()
    out = tmp_path / "rec"
    space = _space(tmp_path / "space.yaml", duration_s=8, settle_s=0,
                   vary=[{"node": "camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate",
                          "values": [5, 10]}])
    proc = subprocess.Popen([str(BIN), "sweep", str(APP), "--space", str(space), "--out", str(out),
                             "--duration", "3"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    line, tags, ports = kill_mid_recording(proc, out, "hough_circles", 1)  # the detector dies during the recording
    lines = [line]
    assert lines[0].startswith("error: run camera-publish_rate-10: "), line
    # the recorder process is up when the detector is killed; whether rosbag had subscribed yet
    # and record-cpu sampled (the runner's last waits) or it was recording is a race on a
    # loaded machine: all are mid-run
    assert re.search(r"node /?detector \(pid \d+", lines[0]), lines[0]  # roslaunch names it without the slash
    assert re.search("during the recording|while waiting for (rosbag record|record-cpu to sample)", lines[0]), lines[0]
    _nothing_left(out, tags, ports)
    _one_line_then_consistent(out, ["camera-publish_rate-5.bag"])


def test_bad_input_is_one_line_before_anything_runs(tmp_path: Path) -> None:
    _require_ros()
    space = _space(tmp_path / "space.yaml", vary=[{"node": "camera", "parameter": {"name": "publish_rate"},
                                                   "arg": "frame_rate", "values": [5]}])
    out = tmp_path / "rec"
    done = _cli("sweep", str(APP), "--space", str(space), "--out", str(out))
    assert done.returncode == 2
    assert done.stderr.strip().count("\n") == 0 and "arg 'frame_rate' is not declared" in done.stderr
    missing = _cli("sweep", str(tmp_path / "nope.launch"), "--space", str(space), "--out", str(out))
    assert missing.returncode == 2 and "launch file not found" in missing.stderr
    assert not out.exists() or not any(out.iterdir())


# a ROS package of our own for the cases Debian's nodes do not show: a node that advertises
# a topic and never publishes on it
QUIET_NODE = """#!/usr/bin/python3
import rospy
from std_msgs.msg import String
rospy.init_node("quiet")
pub = rospy.Publisher("~never", String, queue_size=1)
rospy.spin()
"""


def ros_package(pkgs: Path, name: str, scripts: dict[str, str]) -> Path:
    """A ROS package ``pkgs/name`` (for ``ROS_PACKAGE_PATH=pkgs``) with executable ``scripts``."""
    pkg = pkgs / name
    pkg.mkdir(parents=True)
    (pkg / "package.xml").write_text(f'<?xml version="1.0"?><package format="2"><name>{name}</name>'
                                     '<version>0.0.1</version><description>test</description>'
                                     '<maintainer email="t@t">t</maintainer><license>MIT</license></package>')
    for file, text in scripts.items():
        (pkg / file).write_text(text)
        (pkg / file).chmod(0o755)
    return pkg


def test_a_topic_that_never_publishes_is_one_line(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _require_ros()
    ros_package(tmp_path / "pkgs", "perfros_quiet", {"quiet.py": QUIET_NODE})
    launch = tmp_path / "quiet.launch"
    launch.write_text('<launch><arg name="rate" default="5"/>'
                      '<node name="quiet" pkg="perfros_quiet" type="quiet.py"/></launch>')
    space = _space(tmp_path / "space.yaml", startup_timeout_s=4,
                   vary=[{"node": "quiet", "parameter": {"name": "rate"}, "arg": "rate", "values": [5]}])
    monkeypatch.setenv("ROS_PACKAGE_PATH", str(tmp_path / "pkgs"))
    out = tmp_path / "rec"
    done = _cli("sweep", str(launch), "--space", str(space), "--out", str(out))
    assert done.returncode == 2, done.stderr
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert lines == ["error: run quiet-rate-5: topic(s) /quiet/never never published within 4 s"], done.stderr
    _nothing_left(out, set(), set())
    assert not (out / "manifest.yaml").exists()


# Debian's rosbag reader: the value of an int parameter in a node's dynamic_reconfigure
# parameter_updates (what the node itself runs with)
BAG_INT_PARAM = r"""
import sys, rosbag
with rosbag.Bag(sys.argv[1]) as bag:
    for _topic, msg, _t in bag.read_messages(topics=[sys.argv[2]]):
        print([p.value for p in msg.ints if p.name == sys.argv[3]][0])
        break
"""


def test_a_param_entry_reaches_the_node(tmp_path: Path) -> None:
    """``param:`` sets a private parameter the launch file does not set; the node's own
    dynamic_reconfigure report, recorded in the bag, shows the value of each run."""
    _require_ros()
    space = _space(tmp_path / "space.yaml", duration_s=2, settle_s=0,
                   vary=[{"node": "detector", "parameter": {"name": "gaussian_blur_size"},
                          "param": "gaussian_blur_size", "values": [5, 11]}])
    out = tmp_path / "rec"
    done = _cli("sweep", str(APP), "--space", str(space), "--out", str(out))
    assert done.returncode == 0, done.stderr
    manifest = load_manifest(out / "manifest.yaml")
    assert [e.settings["detector"] for e in manifest.recordings] == [5, 11]
    for e in manifest.recordings:
        shown = subprocess.run([ROS_PY, "-c", BAG_INT_PARAM, str(e.path), "/detector/parameter_updates",
                                "gaussian_blur_size"], capture_output=True, text=True, timeout=60, check=True,
                               env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
        assert int(shown.stdout) == e.settings["detector"], (e.name, shown.stdout)
