"""Nodelets on Debian's real nodes (fixtures/nodelet: image_publisher -> one nodelet manager
with opencv_apps' people_detect and smoothing loaded into it): ``sweep`` -> ``init`` ->
``characterise``, and the bad inputs refused before anything starts.

Checked against independent sources: the membership against the launch file's own XML
(``args="load TYPE MANAGER"``); the split CPU against the unsplit measurement of the same
runs (the system without ``container:``): per run, what the nodelets and their manager are
given adds up to what the manager and the loaders' processes measured."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
import yaml

from perfros_bag.characterisation.manifest import load_manifest
from perfros_bag.characterisation.table import characterise
from perfros_bag.sweep.graph import read_graph
from perfros_bag.system.systemfile import load_system, parse_system
from tests.conftest import FIXTURES

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).with_name("perfros-bag")
LAUNCH = FIXTURES / "nodelet" / "nodelet.launch"


def _require_ros() -> None:
    for tool in ("/usr/bin/roslaunch", "/usr/lib/nodelet/nodelet", "/usr/share/opencv_apps/nodelet_plugins.xml"):
        assert os.path.exists(tool), f"{tool} missing: make setup-debs (see the Makefile's DEBS)"


def _cli(*args: str, timeout: float = 300) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(BIN), *args], capture_output=True, text=True, timeout=timeout)


def _space(path: Path) -> Path:
    doc = yaml.safe_load((FIXTURES / "nodelet" / "space.yaml").read_text())
    doc.update(duration_s=5, settle_s=0.5)  # record-cpu's first samples come late under load
    doc["vary"][0]["values"] = [1.1, 1.4]
    doc["vary"][0]["default"] = 1.4
    path.write_text(yaml.safe_dump(doc, sort_keys=False))
    return path


def _from_xml() -> dict[str, tuple[str, str]]:
    """nodelet name -> (type, manager) read from the launch file's XML itself."""
    out = {}
    for n in ET.parse(LAUNCH).getroot().iter("node"):
        words = (n.get("args") or "").split()
        if n.get("pkg") == "nodelet" and words[:1] == ["load"]:
            out[n.get("name") or ""] = (words[1], words[2])
    return out


@pytest.mark.slow  # a sweep of 7 runs of real nodelets (~3 min): `make test-slow`
def test_sweep_init_characterise_per_nodelet(tmp_path: Path) -> None:
    _require_ros()
    runs = tmp_path / "runs"
    done = _cli("sweep", str(LAUNCH), "--space", str(_space(tmp_path / "space.yaml")), "--out", str(runs))
    assert done.returncode == 0, done.stderr
    manifest = load_manifest(runs / "manifest.yaml")
    alone = [e for e in manifest.recordings if e.standalone]
    assert len(manifest.recordings) == 4 and len(alone) == 1  # 3 one-at-a-time + the standalone run
    assert sorted(alone[0].standalone) == ["people", "smooth"]
    graph = read_graph(runs / "graph.yaml")
    xml = _from_xml()
    for name, (kind, manager) in xml.items():
        node = graph.node("/" + name)
        assert node is not None and node.nodelet == kind and node.container == "/" + manager
        own = [t.name for t in graph.topics if node.name in t.publishers
               and not (t.type or "").startswith(("bond/", "rosgraph_msgs/"))]
        assert own and all(t.startswith(f"/{name}/") for t in own)

    done = _cli("init", str(runs), "--out", str(tmp_path / "system.yaml"))
    assert done.returncode == 0, done.stderr
    system = load_system(tmp_path / "system.yaml")
    for name, (_, manager) in xml.items():
        node = system.node[name]
        assert node.container == manager
        assert f"/{name}/image" in node.topics and not any("bond" in t for t in node.topics)
    assert system.node["people"].parameter is not None and len(system.node["people"].settings) == 2
    assert system.node["vision_manager"].container is None
    assert not any("bond" in t for n in system.nodes for t in n.topics)

    split = characterise(manifest.recordings, system)
    assert split.splits and not split.failures
    assert sorted(split.splits[0].reference) == ["people", "smooth"]  # anchored on the standalone run
    raw_doc = yaml.safe_load((tmp_path / "system.yaml").read_text())
    for n in raw_doc["nodes"]:
        n.pop("container", None)
        n.pop("copy_cpu_per_MBps", None)
    raw = characterise([e for e in manifest.recordings if not e.standalone], parse_system(raw_doc, "raw"))

    def per_node(rows: list, rec: str) -> dict[str, float]:
        return {r.node: r.cpu_units_mean for r in rows if r.recording == rec and r.cpu_units_mean is not None}

    for e in manifest.recordings:
        if e.standalone:
            assert not [r for r in split.rows if r.recording == e.name]
            continue
        got, measured = per_node(split.rows, e.name), per_node(raw.rows, e.name)
        hosted = ("vision_manager", "people", "smooth")
        assert sum(got[n] for n in hosted) == pytest.approx(sum(measured[n] for n in hosted), rel=1e-3, abs=0.05)
        assert got["people"] > measured["people"]  # its share of the manager, not its loader's bond keeping
    # the detector's work moves with its own setting: more scales (1.1) cost more than fewer (1.4)
    cpu = {s.value: s.cpu for s in system.node["people"].settings}
    assert cpu[1.1] > cpu[1.4]
    # the copy price on the manager, by hand from the unsplit rows of every run: the
    # standalone run's total CPU over the in-manager run's at the same values (the defaults),
    # per MB/s of the one more copy of the camera's frames two standalone receivers take
    from dataclasses import replace  # the standalone run's rows as measured (not left out as a split does)

    every = characterise([replace(e, standalone=()) for e in manifest.recordings], parse_system(raw_doc, "raw")).rows
    alone_run = alone[0].name
    twin = next(e.name for e in manifest.recordings if not e.standalone and e.settings == alone[0].settings)

    def total(rec: str) -> float:
        return sum(per_node(every, rec).values())

    frames = next(r.bandwidth_kBps for r in every if r.recording == alone_run and r.topic == "/camera/image_raw")
    assert frames
    assert system.node["vision_manager"].copy_cpu_per_MBps == pytest.approx(  # < 0 (noise) is drafted as 0
        max(0.0, (total(alone_run) - total(twin)) / (frames / 1000)), rel=1e-3, abs=1e-4)

    # deploy across two emulated computers: the camera on the robot, the manager and its
    # nodelets (membership kept) on the server, each nodelet loaded into its manager there
    doc = yaml.safe_load((tmp_path / "system.yaml").read_text())
    robot = doc["computers"][0]["name"]
    doc["computers"].append({"name": "server", "kind": "server", "capacity": 200})
    doc["links"] = [{"between": [robot, "server"], "bandwidth_kBps": 20000}]
    for n in doc["nodes"]:
        n["residence"] = [robot] if n["name"] == "camera" else ["server"]
    (tmp_path / "two.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    for args in (("characterise", str(runs), "--system", str(tmp_path / "two.yaml"), "--out", str(tmp_path / "c.csv")),
                 ("fit", str(tmp_path / "two.yaml"), str(tmp_path / "c.csv"), "--out", str(tmp_path / "m.json")),
                 ("solve", str(tmp_path / "m.json"), "--problem", "1", "--method", "exact", "--out",
                  str(tmp_path / "plan.json")),
                 ("deploy", str(tmp_path / "plan.json"), str(LAUNCH), "--space", str(tmp_path / "space.yaml"),
                  "--out", str(tmp_path / "dep"), "--duration", "4", "--system", str(tmp_path / "two.yaml"))):
        done = _cli(*args)
        assert done.returncode == 0, (args[0], done.stderr)
    deployed = json.loads((tmp_path / "dep" / "deploy.json").read_text())
    assert {n: x["computer"] for n, x in deployed["nodes"].items()} == {
        "/camera": robot, "/vision_manager": "server", "/people": "server", "/smooth": "server"}
    assert deployed["leftover_cgroups"] == [] and deployed["leftover_namespaces"] == []
    valid = json.loads((tmp_path / "dep" / "validation.json").read_text())
    assert valid["overall"]["passed"], valid["overall"]
    # export --launch keeps the membership: each loader loads into its manager, on its machine
    done = _cli("export", str(tmp_path / "plan.json"), "--format", "roslaunch", "--launch", str(LAUNCH), "--space",
                str(tmp_path / "space.yaml"), "--system", str(tmp_path / "two.yaml"), "--out",
                str(tmp_path / "planned.launch"))
    assert done.returncode == 0, done.stderr
    planned = {n.get("name"): n for n in ET.parse(tmp_path / "planned.launch").getroot().iter("node")}
    for name, (kind, manager) in xml.items():
        assert (planned[name].get("args") or "").split() == ["load", kind, manager]
        assert planned[name].get("machine") == planned[manager].get("machine") == "server"


@pytest.mark.parametrize(("edit", "message"), [
    (("args=\"manager\"", "args=\"manager\" if=\"false\""),
     "into manager /vision_manager, which the launch file never starts"),
    (("opencv_apps/smoothing", "opencv_apps/no_such_nodelet"), "class opencv_apps/no_such_nodelet does not exist"),
])
def test_bad_nodelets_refused_before_anything_starts(tmp_path: Path, edit: tuple[str, str], message: str) -> None:
    _require_ros()
    launch = tmp_path / "nodelet.launch"
    launch.write_text(LAUNCH.read_text().replace(*edit).replace("$(dirname)/../app", str(FIXTURES / "app")))
    out = tmp_path / "runs"
    done = _cli("sweep", str(launch), "--space", str(FIXTURES / "nodelet" / "space.yaml"), "--out", str(out),
                timeout=120)
    assert done.returncode == 2
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and message in lines[0] and str(launch) in lines[0], done.stderr
    assert not out.exists()  # nothing started, nothing written


def _two_computer_system(path: Path, residence: dict[str, str], container: bool) -> Path:
    """The fixture's nodes on a robot and a server, each where ``residence`` puts it."""
    nodes = []
    for name in ("camera", "vision_manager", "people", "smooth"):
        node: dict[str, object] = {"name": name, "weight": 0.25, "residence": [residence[name]],
                                   "settings": [{"cpu": 5, "performance": 1}]}
        if container and name in ("people", "smooth"):
            node["container"] = "vision_manager"
        nodes.append(node)
    path.write_text(yaml.safe_dump({"computers": [{"name": "robot", "kind": "robot", "capacity": 100},
                                                  {"name": "server", "kind": "server", "capacity": 100}],
                                    "nodes": nodes}, sort_keys=False))
    return path


@pytest.mark.parametrize("edit", [None, ("args=\"manager\"", "args=\"manager\" if=\"false\""),
                                  ("opencv_apps/smoothing", "opencv_apps/no_such_nodelet")])
def test_deploy_refuses_bad_nodelets_and_a_split_before_anything_starts(tmp_path: Path,
                                                                        edit: tuple[str, str] | None) -> None:
    """A plan that puts smooth on the robot and its manager on the server. Its system.yaml has
    no ``container:`` (so nothing but the launch file says they share a process): deploy
    refuses it from the launch file's own membership; a launch file whose manager never
    starts or whose nodelet class no package exports is refused first."""
    _require_ros()
    launch = tmp_path / "nodelet.launch"
    text = LAUNCH.read_text().replace("$(dirname)/../app", str(FIXTURES / "app"))
    launch.write_text(text.replace(*edit) if edit is not None else text)
    where = {"camera": "robot", "vision_manager": "server", "people": "server", "smooth": "robot"}
    system = _two_computer_system(tmp_path / "s.yaml", where, container=False)
    done = _cli("solve", str(system), "--problem", "1", "--method", "exact", "--out", str(tmp_path / "plan.json"))
    assert done.returncode == 0, done.stderr
    out = tmp_path / "dep"
    done = _cli("deploy", str(tmp_path / "plan.json"), str(launch), "--space", str(FIXTURES / "nodelet" / "space.yaml"),
                "--out", str(out), "--duration", "2", "--system", str(system), timeout=120)
    assert done.returncode == 2
    lines = [x for x in done.stderr.splitlines() if x.strip() and not x.startswith("warning:")]
    assert len(lines) == 1, done.stderr
    if edit is None:
        assert lines[0].startswith(f"error: {tmp_path / 'plan.json'}: container vision_manager: node smooth on robot "
                                   "but its container vision_manager on server"), lines[0]
    else:
        assert str(launch) in lines[0] and ("never starts" in lines[0] or "no_such_nodelet does not exist" in lines[0])
    assert not out.exists()  # nothing started, nothing written
    # export --launch refuses the same plan with the same line, writing nothing
    done = _cli("export", str(tmp_path / "plan.json"), "--format", "roslaunch", "--launch", str(launch), "--space",
                str(FIXTURES / "nodelet" / "space.yaml"), "--system", str(system), "--out", str(tmp_path / "x.launch"))
    assert done.returncode == 2
    assert [x for x in done.stderr.splitlines() if x.strip() and not x.startswith("warning:")] == lines
    assert not (tmp_path / "x.launch").exists()
    # with the membership in system.yaml the solvers cannot split it: residence names both and the container
    system = _two_computer_system(tmp_path / "c.yaml", where, container=True)
    done = _cli("solve", str(system), "--problem", "1", "--method", "greedy", "--out", str(tmp_path / "p2.json"))
    assert done.returncode == 2 and not (tmp_path / "p2.json").exists()
    assert "container 'vision_manager': residence: nodes 'vision_manager' (allowed on server) and 'smooth' " \
           "(allowed on robot)" in done.stderr, done.stderr
