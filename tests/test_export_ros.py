"""``export --format roslaunch --launch APP.launch --space space.yaml``: the user's own launch
file, planned, checked against Debian's roslaunch itself.

- every node of the written file resolves with ``roslaunch --nodes`` and ``--args``, to the
  same command line as the user's file run with the plan's values, and ``--dump-params``
  gives the same parameters; roslaunch's own loader puts every node on its plan computer;
- with every machine's address local (``localhost``, ``127.0.0.1``), ``roslaunch`` starts it
  (the sweep's own run: roscore, roslaunch, rosbag record), the recording validates against
  the plan (the ``validate`` verb, eq 10) and nothing is left running;
- several robots from one launch file (docs/casestudy-real.md's app2.launch): each robot's
  nodes on its own machine;
- bad input: one line, exit 2, nothing written.
"""

from __future__ import annotations

import json
import os
import subprocess
import uuid
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.rosrun.processes import leftover_processes
from perfros_bag.sweep.launchfile import read_launch
from perfros_bag.sweep.runner import record_run
from perfros_bag.sweep.space import Run, load_space
from tests.conftest import FIXTURES
from tests.test_export import LOADER
from tests.test_sweep_e2e import BIN, ROS_PY, _bag_rates, _cli, _nothing_left, _require_ros

pytestmark = pytest.mark.ros

APP = FIXTURES / "app" / "app.launch"
SPACE = FIXTURES / "app" / "space.yaml"
APP2 = FIXTURES / "casestudy_real" / "app2.launch"
IMAGE = "/camera/image_raw"


def _plan(path: Path, nodes: dict[str, tuple[str, str | None, float | None, dict[str, float]]]) -> Path:
    """A plan.json: node -> (computer, parameter, value, {topic: planned Hz})."""
    computers = sorted({c for c, *_ in nodes.values()})
    doc = {"format": "perfros-bag/plan@1", "problem": 1, "method": "test", "status": "optimal",
           "computers": {c: {"kind": "robot", "capacity": 100, "cpu": 10} for c in computers}, "links": [],
           "nodes": {n: {"computer": c, "parameter": p, "value": v, "cpu": 5, "performance": 50, "weight": 1.0,
                         "topics": {t: {"frequency_hz": hz, "bandwidth_kBps": None} for t, hz in topics.items()}}
                     for n, (c, p, v, topics) in nodes.items()}}
    path.write_text(json.dumps(doc))
    return path


def _export(plan: Path, launch: Path, space: Path, out: Path) -> subprocess.CompletedProcess[str]:
    """``perfros-bag export PLAN --format roslaunch --launch LAUNCH --space SPACE --out OUT``."""
    return _cli("export", str(plan), "--format", "roslaunch", "--launch", str(launch), "--space", str(space),
                "--out", str(out))


def _roslaunch(*args: str) -> str:
    done = subprocess.run(["roslaunch", *args], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout


def _loaded(launch: Path, *args: str) -> dict[str, Any]:
    """Debian's roslaunch loader: each node's machine and each machine's address."""
    r = subprocess.run([ROS_PY, "-c", LOADER, str(launch), *args], capture_output=True, text=True, timeout=60,
                       env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert r.returncode == 0, r.stderr
    nodes, machines, clear = {}, {}, []
    for line in r.stdout.splitlines():
        kind, name, value = (line.split(" ", 2) + [""])[:3]
        if kind == "clear":
            clear.append(name)
        elif kind == "node":
            nodes[name] = value
        elif kind == "machine" and name:  # "": roslaunch's own local machine
            machines[name] = value
    return {"nodes": nodes, "machines": machines, "clear": clear}


def _same_as_the_users_file(planned: Path, app: Path, args: list[str]) -> list[str]:
    """Every node of ``planned`` resolves with roslaunch --nodes/--args exactly as ``app`` with
    the plan's ``args``, and both set the same parameters; returns the nodes."""
    nodes = _roslaunch("--nodes", str(planned)).split()
    assert sorted(nodes) == sorted(_roslaunch("--nodes", str(app), *args).split())
    for node in nodes:
        assert _roslaunch("--args", node, str(planned)) == _roslaunch("--args", node, str(app), *args), node
    assert yaml.safe_load(_roslaunch("--dump-params", str(planned))) == \
        yaml.safe_load(_roslaunch("--dump-params", str(app), *args))
    return nodes


def test_the_users_launch_file_planned_resolves_as_theirs_on_the_plan_computers(tmp_path: Path) -> None:
    _require_ros()
    plan = _plan(tmp_path / "plan.json", {"camera": ("robot1", "publish_rate", 7.0, {}),
                                          "detector": ("server", "canny_threshold", 150.00000001, {})})
    out = tmp_path / "planned.launch"
    done = _export(plan, APP, SPACE, out)
    assert done.returncode == 0, done.stderr
    nodes = _same_as_the_users_file(out, APP, ["camera_rate:=7", "canny_threshold:=150"])
    assert sorted(nodes) == ["/camera", "/detector"]
    loaded = _loaded(out)
    assert loaded["nodes"] == {"camera": "robot1", "detector": "server"}
    assert loaded["machines"] == {"robot1": "robot1", "server": "server"}  # addresses default to the names
    assert _loaded(out, "robot1_address:=10.0.0.7")["machines"]["robot1"] == "10.0.0.7"
    # the plan's values go through space.yaml's args: setting one still reaches the node
    params = yaml.safe_load(_roslaunch("--dump-params", str(out), "camera_rate:=12"))
    assert params["/camera/publish_rate"] == 12 and params["/detector/canny_threshold"] == 150

    # a node the plan does not know keeps its launch defaults, no machine, and is listed
    only = _plan(tmp_path / "camera.json", {"camera": ("robot1", "publish_rate", 5.0, {})})
    out2 = tmp_path / "camera.launch"
    done = _export(only, APP, SPACE, out2)
    assert done.returncode == 0, done.stderr
    assert "not in the plan" in done.stderr and "detector" in done.stderr
    _same_as_the_users_file(out2, APP, ["camera_rate:=5"])
    assert _loaded(out2)["nodes"] == {"camera": "robot1", "detector": ""}
    comments = [c.text or "" for c in ET.parse(out2, ET.XMLParser(target=ET.TreeBuilder(insert_comments=True)))
                .getroot().iter(ET.Comment)]
    assert any("plan does not know" in c and "/detector" in c for c in comments)


# Every kind of value a launch file can give a node, and XML's special characters in them.
RICH = """<launch>
  <arg name="camera_rate" default="10" />
  <arg name="canny_threshold" default="200" />
  <arg name="mode" default="fast" />
  <env name="PERFROS_NOTE" value="a &amp; b &lt;c&gt; &quot;q&quot; 'x' $(arg mode)" />
  <rosparam param="/global/list">[1, 2.5, "a&lt;b"]</rosparam>
  <param name="/global/mode" value="$(arg mode)" />
  <rosparam param="/global/padded">"  spaces at both ends  "</rosparam>
  <group ns="cams">
    <node name="camera" pkg="image_publisher" type="image_publisher" args="IMAGE" respawn="true" output="screen"
          clear_params="true" respawn_delay="2.5">
      <param name="publish_rate" value="$(arg camera_rate)" type="double" />
      <param name="note" value="rate=$(arg camera_rate) &amp; &lt;more&gt;" />
      <param name="flag" value="true" />
      <rosparam>nested: {a: 1, b: [x, y]}</rosparam>
    </node>
  </group>
  <machine name="mine" address="localhost" user="someone" timeout="20" />
  <node name="extra" pkg="image_publisher" type="image_publisher" machine="mine" args="x" />
  <node name="detector" pkg="opencv_apps" type="hough_circles" launch-prefix="nice -n 5" required="true"
        if="$(eval canny_threshold > 100)">
    <remap from="image" to="cams/camera/image_raw" />
    <remap from="$(arg mode)_in" to="$(arg mode)_out" />
    <param name="canny_threshold" value="$(arg canny_threshold)" />
  </node>
</launch>
"""


def test_every_kind_of_value_and_xml_characters_survive(tmp_path: Path) -> None:
    """Parameters of every type (lists, nested, strings with XML's characters), <env>, remaps,
    respawn/required/output/launch-prefix: the written file resolves exactly as the user's; an
    arg space.yaml varies reaches every place the user's file used it, inside text too."""
    _require_ros()
    app = tmp_path / "my--app" / "rich.launch"  # "--" cannot go into an XML comment as it is
    app.parent.mkdir()
    app.write_text(RICH.replace("IMAGE", str(FIXTURES / "app" / "circles.png")))
    space = tmp_path / "space.yaml"
    space.write_text(yaml.safe_dump({"vary": [
        {"node": "/cams/camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate", "values": [5.0, 10.0]},
        {"node": "detector", "parameter": {"name": "canny_threshold"}, "arg": "canny_threshold",
         "values": [100, 200]}]}))
    plan = _plan(tmp_path / "plan.json", {"cams_camera": ("robot1", "publish_rate", 7.5, {}),
                                          "detector": ("robot1", "canny_threshold", 120.0, {})})
    out = tmp_path / "planned.launch"
    done = _export(plan, app, space, out)
    assert done.returncode == 0, done.stderr
    text = out.read_text()
    assert "&amp;" in text and "&lt;" in text and "&quot;" in text  # escaped by the writer, not raw
    _same_as_the_users_file(out, app, ["camera_rate:=7.5", "canny_threshold:=120"])
    params = yaml.safe_load(_roslaunch("--dump-params", str(out), "camera_rate:=12.5"))
    assert params["/cams/camera/publish_rate"] == 12.5 and params["/cams/camera/note"] == "rate=12.5 & <more>"
    assert params["/detector/canny_threshold"] == 120
    # the node the plan does not know keeps the user's machine, written with what the file gave
    loaded = _loaded(out)
    assert loaded["nodes"] == {"camera": "robot1", "detector": "robot1", "extra": "mine"}
    assert loaded["machines"]["mine"] == "localhost"
    assert loaded["clear"] == _loaded(app, "camera_rate:=7.5", "canny_threshold:=120")["clear"] == ["/cams/camera/"]
    camera = next(n for n in ET.parse(out).getroot().iter("node") if n.get("name") == "camera")
    assert {k: camera.get(k) for k in ("respawn", "respawn_delay", "output", "clear_params")} == {
        "respawn": "true", "respawn_delay": "2.5", "output": "screen", "clear_params": "true"}
    mine = next(m for m in ET.parse(out).getroot().iter("machine") if m.get("name") == "mine")
    assert mine.attrib == {"name": "mine", "address": "localhost", "user": "someone", "timeout": "20.0"}


def test_exported_file_runs_with_local_addresses_records_and_validates(tmp_path: Path) -> None:
    """roslaunch starts the written file with its machines at local addresses (roslaunch runs a
    machine locally when its address is one of this host's: localhost, 127.x); the sweep's
    run records it; the validate verb checks the recording against the plan."""
    _require_ros()
    plan = _plan(tmp_path / "plan.json", {"camera": ("robot1", "publish_rate", 7.0, {IMAGE: 7.0}),
                                          "detector": ("server", "canny_threshold", 150.0, {})})
    planned = tmp_path / "planned.launch"
    done = _export(plan, APP, SPACE, planned)
    assert done.returncode == 0, done.stderr
    space = load_space(SPACE).with_duration(3)
    run = Run("exported", {}, {"robot1_address": "localhost", "server_address": "127.0.0.1"}, {}, 1)
    tag = "x" + uuid.uuid4().hex[:9]
    out = tmp_path / "run"
    out.mkdir()
    graph = record_run(read_launch(planned), space, run, out, run_id=tag)
    _nothing_left(out, {tag}, set())
    assert leftover_processes(tag) == []
    assert sorted(n.name for n in graph.nodes if n.launched) == ["/camera", "/detector"]
    assert all(n.pid for n in graph.nodes if n.launched)
    bag = out / "exported.bag"
    measured = _bag_rates(bag)[IMAGE]  # Debian's rosbag reader
    assert abs(measured / 7.0 - 1) < 0.1, measured  # the camera ran at the plan's rate, through the arg
    assert _bag_rates(bag)["/detector/circles"] > 0  # and the detector on its images
    checked = subprocess.run([str(BIN), "validate", str(bag), str(plan), "--cpu", str(out / "exported.cpu.csv"),
                              "--out", str(tmp_path / "validation.json")], capture_output=True, text=True, timeout=120)
    assert checked.returncode in (0, 1), checked.stderr  # 1: deviates from the plan by more than 5 %
    assert "Traceback" not in checked.stderr
    validation = json.loads((tmp_path / "validation.json").read_text())
    assert (checked.returncode == 0) == (validation["overall"]["deviation_pct"] <= 5.0)
    camera = next(n for n in validation["nodes"] if n["node"] == "camera")
    topic = next(t for t in camera["topics"] if t["topic"] == IMAGE)
    assert topic["f_expected"] == 7.0 and abs(topic["f_measured"] / measured - 1) < 0.01


APP2_SPACE = {"duration_s": 3, "settle_s": 1, "design": "one-at-a-time", "vary": [
    {"node": f"/robot{k}/{node}", "parameter": {"name": p}, "arg": f"robot{k}_{arg}", "values": values}
    for k in (1, 2) for node, p, arg, values in (("people", "scale0", "scale0", [1.05, 1.1]),
                                                 ("smooth", "kernel_size", "kernel", [3, 7]))]}


def test_several_robots_from_one_launch_file_each_on_its_machine(tmp_path: Path) -> None:
    _require_ros()
    space = tmp_path / "space.yaml"
    space.write_text(yaml.safe_dump(APP2_SPACE))
    nodes: dict[str, tuple[str, str | None, float | None, dict[str, float]]] = {}
    for k, scale0, kernel in ((1, 1.05, 3), (2, 1.1, 5)):
        nodes[f"robot{k}_camera"] = (f"robot{k}", None, None, {})
        nodes[f"robot{k}_people"] = (f"robot{k}", "scale0", scale0, {})
        nodes[f"robot{k}_smooth"] = ("server" if k == 2 else f"robot{k}", "kernel_size", float(kernel), {})
    plan = _plan(tmp_path / "plan.json", nodes)
    out = tmp_path / "planned.launch"
    done = _export(plan, APP2, space, out)
    assert done.returncode == 0, done.stderr
    args = ["robot1_scale0:=1.05", "robot1_kernel:=3", "robot2_scale0:=1.1", "robot2_kernel:=5"]
    assert len(_same_as_the_users_file(out, APP2, args)) == 6
    script_nodes = subprocess.run([ROS_PY, "-c", LOADER, str(out)], capture_output=True, text=True, timeout=60,
                                  env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"}).stdout
    placed = {line.split()[1]: line.split()[2] for line in script_nodes.splitlines() if line.startswith("fullnode ")}
    assert placed == {f"/robot{k}/{n}": ("server" if (k, n) == (2, "smooth") else f"robot{k}")
                      for k in (1, 2) for n in ("camera", "people", "smooth")}
    assert set(_loaded(out)["machines"]) == {"robot1", "robot2", "server"}


def _one_line(done: subprocess.CompletedProcess[str], out: Path, *needles: str) -> None:
    assert done.returncode == 2, done.stderr
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), done.stderr
    assert "Traceback" not in done.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]
    assert not out.exists()
    assert [p.name for p in out.parent.iterdir() if p.name.startswith(".")] == []


def test_bad_input_is_one_line_and_writes_nothing(tmp_path: Path) -> None:
    _require_ros()
    out = tmp_path / "x.launch"
    # a plan whose nodes are not in the launch file: named
    stray = _plan(tmp_path / "stray.json", {"camera": ("robot1", "publish_rate", 7.0, {}),
                                            "detector": ("robot1", "canny_threshold", 100.0, {}),
                                            "tracker": ("robot1", None, None, {}),
                                            "mapper": ("robot1", None, None, {})})
    _one_line(_export(stray, APP, SPACE, out), out,
              str(APP), "tracker, mapper", "not in it")
    # a space.yaml that does not match the plan's parameters
    other = _plan(tmp_path / "other.json", {"camera": ("robot1", "frame_rate", 7.0, {}),
                                            "detector": ("robot1", "canny_threshold", 100.0, {})})
    _one_line(_export(other, APP, SPACE, out), out,
              str(SPACE), "'publish_rate'", "'frame_rate'")
    plan = _plan(tmp_path / "plan.json", {"camera": ("robot1", "publish_rate", 7.0, {}),
                                          "detector": ("robot1", "canny_threshold", 100.0, {})})
    only_camera = tmp_path / "camera-space.yaml"
    only_camera.write_text(yaml.safe_dump({"vary": [yaml.safe_load(SPACE.read_text())["vary"][0]]}))
    _one_line(_export(plan, APP, only_camera, out), out,
              str(only_camera), "detector", "canny_threshold")
    # a launch file roslaunch cannot read: its error, with the file
    broken = tmp_path / "broken.launch"
    broken.write_text(APP.read_text().replace("$(arg canny_threshold)", "$(arg canny)"))
    _one_line(_export(plan, broken, SPACE, out), out,
              str(broken), "roslaunch cannot read it", "'canny'")
    typed = tmp_path / "typed.launch"
    typed.write_text(APP.read_text().replace('<node name="camera"', '<node name="camera" respawn="perhaps"'))
    _one_line(_export(plan, typed, SPACE, out), out,
              str(typed), "roslaunch cannot read it", "perhaps")
    # two ROS nodes that are one plan node (/cam/era and /cam_era are both cam_era): both named
    clash = tmp_path / "clash.launch"
    clash.write_text(APP.read_text().replace(
        "</launch>", '<group ns="detector"><node name="x" pkg="opencv_apps" type="hough_circles" /></group>'
                     '<node name="detector_x" pkg="opencv_apps" type="hough_circles" /></launch>'))
    clashing = _plan(tmp_path / "clash.json", {"camera": ("robot1", "publish_rate", 7.0, {}),
                                               "detector": ("robot1", "canny_threshold", 100.0, {}),
                                               "detector_x": ("robot1", None, None, {})})
    _one_line(_export(clashing, clash, SPACE, out), out,
              str(clash), "ROS nodes /detector/x and /detector_x both are the plan's node detector_x")
    # --launch without --space, or with the ROS 2 format
    _one_line(_cli("export", str(plan), "--format", "roslaunch", "--out", str(out), "--launch", str(APP)), out,
              "--space")
    _one_line(_cli("export", str(plan), "--format", "ros2-params", "--out", str(out), "--launch", str(APP),
                   "--space", str(SPACE)), out, "--format roslaunch")
