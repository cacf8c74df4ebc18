"""Nodelets: membership (roslaunch's resolution -> graph), system.yaml ``container`` (a
coresidence the checker and the plan reader keep), and the manager's CPU split among its
nodelets (perfros_bag/characterisation/containers.py).

The split is checked against numbers the test makes itself: per-nodelet CPU chosen at random,
the manager's total their sum; and, with noise, against the least-squares optimality condition
(no single estimate can be moved without raising the squared error over the runs)."""

from __future__ import annotations

import itertools
import json
import random
import re
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from perfros_bag.characterisation.containers import fit_split, split_containers
from perfros_bag.characterisation.csvfile import Row
from perfros_bag.characterisation.manifest import RecordingEntry
from perfros_bag.errors import InputError
from perfros_bag.solver.check import check_plan
from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic, read_graph, write_graph
from perfros_bag.sweep.launchfile import Resolved, ResolvedNode
from perfros_bag.sweep.nodelets import check_nodelets, nodelets_of, standalone_argv, with_membership
from perfros_bag.system.planfile import load_plan
from perfros_bag.system.systemfile import parse_system

BIN = Path(sys.executable).with_name("perfros-bag")


def _node(name: str, args: str, remaps: tuple[tuple[str, str], ...] = (), ns: str = "/") -> ResolvedNode:
    return ResolvedNode("nodelet", "nodelet", name, ns, args, remaps, (), None, "x.launch", {})


def _resolved() -> Resolved:
    return Resolved((ResolvedNode("image_publisher", "image_publisher", "camera", "/", "", (), (), None, "", {}),
                     _node("vision_manager", "manager"),
                     _node("people", "load opencv_apps/people_detect vision_manager", (("image", "camera/image_raw"),)),
                     _node("smooth", "load opencv_apps/smoothing /vision_manager", (("image", "camera/image_raw"),))),
                    {}, {})


def test_membership_from_resolution_and_graph(tmp_path: Path) -> None:
    nodelets = nodelets_of(_resolved())
    assert {n: (x.type, x.manager) for n, x in nodelets.items()} == {
        "/people": ("opencv_apps/people_detect", "/vision_manager"),
        "/smooth": ("opencv_apps/smoothing", "/vision_manager")}
    # as the master sees it: the manager publishes and subscribes for its nodelets
    graph = Graph((GraphNode("/camera", 1, "ip"), GraphNode("/people", 2, "nodelet"),
                   GraphNode("/smooth", 3, "nodelet"),
                   GraphNode("/vision_manager", 4, "nodelet")),
                  (GraphTopic("/camera/image_raw", "sensor_msgs/Image", ("/camera",), ("/vision_manager",)),
                   GraphTopic("/people/found", "opencv_apps/RectArrayStamped", ("/vision_manager",), ()),
                   GraphTopic("/smooth/image", "sensor_msgs/Image", ("/vision_manager",), ()),
                   GraphTopic("/vision_manager/bond", "bond/Status", ("/people", "/smooth", "/vision_manager"),
                              ("/people", "/smooth", "/vision_manager"))))
    g = with_membership(graph, nodelets)
    by = {t.name: t for t in g.topics}
    assert by["/people/found"].publishers == ("/people",)
    assert by["/smooth/image"].publishers == ("/smooth",)
    assert by["/camera/image_raw"].subscribers == ("/people", "/smooth")  # both remap image to it
    assert by["/vision_manager/bond"] == graph.topics[3]  # the bond is left as it is
    assert g.node("/people").container == "/vision_manager" and g.node("/people").nodelet == "opencv_apps/people_detect"
    assert g.node("/vision_manager").container is None
    write_graph(tmp_path / "graph.yaml", g)
    assert read_graph(tmp_path / "graph.yaml") == g


def test_manager_never_started_is_one_error() -> None:
    r = _resolved()
    r = Resolved(tuple(n for n in r.nodes if n.name != "vision_manager"), {}, {})
    with pytest.raises(InputError, match=r"node /people: nodelet load .* into manager /vision_manager, which the "
                                         r"launch file never starts"):
        check_nodelets(r, "x.launch")


def test_standalone_argv() -> None:
    argv = ["/usr/lib/nodelet/nodelet", "load", "opencv_apps/smoothing", "vision_manager", "image:=/camera/image_raw",
            "__name:=smooth"]
    assert standalone_argv(argv) == ["/usr/lib/nodelet/nodelet", "standalone", "opencv_apps/smoothing",
                                     "image:=/camera/image_raw", "__name:=smooth"]
    with pytest.raises(InputError):
        standalone_argv(["/usr/lib/nodelet/nodelet", "manager"])


def test_a_standalone_mark_on_a_node_the_launch_file_runs_plainly_is_a_warning() -> None:
    """plan.json ``standalone: true`` on the camera, which the launch file starts as a node of
    its own (no ``nodelet load``): run as the file says, with one warning naming it; the marked
    nodelet still runs standalone, and no mark or only nodelets marked is no warning."""
    import warnings

    from perfros_bag.errors import PerfrosWarning
    from perfros_bag.sweep.nodelets import standalone_nodelets

    nodelets = nodelets_of(_resolved())
    loads = [n.name for n in _resolved().nodes if n.args.startswith("load ")]  # read off the launch file here
    with pytest.warns(PerfrosWarning) as caught:
        assert standalone_nodelets(nodelets, {"camera", "smooth"}, "x.launch") == ("/smooth",)
    (message,) = [str(w.message) for w in caught]
    assert message.startswith("x.launch: node(s) camera: the plan runs them standalone, but the launch file does "
                              "not load them as nodelets") and "smooth" not in message and "camera" not in loads
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert standalone_nodelets(nodelets, set(loads), "x.launch") == ("/people", "/smooth")
        assert standalone_nodelets(nodelets, set(), "x.launch") == ()


# --------------------------------------------------------------------------- the split


def _rows(totals: dict[str, float], values: dict[str, dict[str, float]], loader: float = 0.05,
          alone: dict[str, dict[str, float]] | None = None) -> tuple[list[Row], list[RecordingEntry]]:
    rows, entries = [], []
    for rec, total in totals.items():
        rows.append(Row(rec, "mgr", None, None, None, None, None, 10.0, None, None, total, total * 1.2, 20))
        for k, v in values[rec].items():
            rows.append(Row(rec, k, "p", v, f"/{k}/out", "t", 50, 10.0, 5.0, 1.0, loader, loader, 20))
        entries.append(RecordingEntry(Path(rec), rec, settings=values[rec]))
    for rec, cpus in (alone or {}).items():
        for k, c in cpus.items():
            rows.append(Row(rec, k, "p", values[rec][k], f"/{k}/out", "t", 50, 10.0, 5.0, 1.0, c, c, 20))
        entries.append(RecordingEntry(Path(rec), rec, settings=values[rec], standalone=tuple(cpus)))
    return rows, entries


def _system() -> object:
    return parse_system({"computers": [{"name": "c", "kind": "robot", "capacity": 200}],
                         "nodes": [{"name": "mgr", "weight": 0.4, "settings": [{"cpu": 1, "performance": 1}]},
                                   {"name": "a", "weight": 0.3, "container": "mgr", "parameter": {"name": "p"},
                                    "settings": [{"value": 1, "cpu": 1, "performance": 1},
                                                 {"value": 2, "cpu": 2, "performance": 2}]},
                                   {"name": "b", "weight": 0.3, "container": "mgr", "parameter": {"name": "p"},
                                    "settings": [{"value": 1, "cpu": 1, "performance": 1},
                                                 {"value": 2, "cpu": 2, "performance": 2}]}]}, "t")


def test_split_recovers_chosen_cpu_exactly() -> None:
    rnd = random.Random(4)
    true = {"a": {1: rnd.uniform(5, 30), 2: rnd.uniform(5, 30), 3: rnd.uniform(5, 30)},
            "b": {1: rnd.uniform(1, 9), 2: rnd.uniform(1, 9)}}
    lam = 0.8  # standalone costs 1/0.8 of in-manager
    design = [(1, 1), (2, 1), (3, 1), (1, 2)]  # one at a time around (1, 1)
    totals, values = {}, {}
    for i, (va, vb) in enumerate(design):
        totals[f"r{i}"] = true["a"][va] + true["b"][vb]
        values[f"r{i}"] = {"a": va, "b": vb}
    values["alone"] = {"a": 1, "b": 1}
    rows, entries = _rows(totals, values, alone={"alone": {"a": true["a"][1] / lam, "b": true["b"][1] / lam}})
    s = fit_split(rows, "mgr", ["a", "b"], {"alone": ("a", "b")})
    assert s is not None and s.notes == ()
    assert s.factor == pytest.approx(lam)
    for k in true:
        for v, c in true[k].items():
            assert s.cpu[k][repr(v)] == pytest.approx(c)
    out, _ = split_containers(rows, _system(), entries)
    assert not [r for r in out if r.recording == "alone"]  # a standalone run is not the system's configuration
    for r in out:
        if r.node in true:
            assert r.cpu_units_mean == pytest.approx(true[r.node][r.value] + 0.05)  # + its loader's
        else:
            assert r.cpu_units_mean == pytest.approx(0.0, abs=1e-9)  # the manager: nothing beyond its nodelets


def test_split_with_noise_is_least_squares() -> None:
    rnd = random.Random(7)
    design = list(itertools.product([1, 2, 3], [1, 2]))  # a grid: more runs than unknowns
    totals = {f"r{i}": 10 * va + 3 * vb + rnd.gauss(0, 1.5) for i, (va, vb) in enumerate(design)}
    values = {f"r{i}": {"a": va, "b": vb} for i, (va, vb) in enumerate(design)}
    values["alone"] = {"a": 1, "b": 1}
    rows, _ = _rows(totals, values, alone={"alone": {"a": 11.0, "b": 4.0}})
    s = fit_split(rows, "mgr", ["a", "b"], {"alone": ("a", "b")})
    assert s is not None

    def sse(cpu: dict[str, dict[str, float]]) -> float:
        return sum((totals[r] - cpu["a"][repr(v["a"])] - cpu["b"][repr(v["b"])]) ** 2
                   for r, v in values.items() if r != "alone")

    best = sse(s.cpu)
    assert best == pytest.approx(sum((m - f) ** 2 for m, f in s.runs.values()))
    for k, v in [("a", "2"), ("a", "3"), ("b", "2")]:  # each free value: moving it only raises the error
        for step in (-0.01, 0.01):
            moved = {n: dict(c) for n, c in s.cpu.items()}
            moved[k][v] += step
            assert sse(moved) > best
    # lambda: moving the reference level of both (in the ratio of the standalone anchors) raises it too
    for step in (-0.01, 0.01):
        moved = {n: {x: c + step * s.reference[n] for x, c in cs.items()} for n, cs in s.cpu.items()}
        assert sse(moved) > best


def test_split_without_standalone_run_warns() -> None:
    rows, entries = _rows({"r0": 10.0, "r1": 14.0, "r2": 12.0}, {"r0": {"a": 1, "b": 1}, "r1": {"a": 2, "b": 1},
                                                               "r2": {"a": 1, "b": 2}})
    s = fit_split(rows, "mgr", ["a", "b"], {})
    assert s is not None and any("never ran standalone" in n and "split evenly" in n for n in s.notes)
    assert s.cpu["a"]["1"] == pytest.approx(5.0) and s.cpu["a"]["2"] == pytest.approx(9.0)
    assert s.cpu["b"]["2"] == pytest.approx(7.0)


# --------------------------------------------------------------------------- the model


def _doc(**extra: object) -> dict[str, object]:
    nodes = [{"name": "cam", "weight": 0.25, "settings": [{"cpu": 10, "performance": 1}]},
             {"name": "mgr", "weight": 0.25, "settings": [{"cpu": 1, "performance": 1}]},
             {"name": "a", "weight": 0.25, "container": "mgr", "settings": [{"cpu": 30, "performance": 1}]},
             {"name": "b", "weight": 0.25, "container": "mgr", "settings": [{"cpu": 30, "performance": 1}]}]
    doc = {"computers": [{"name": "robot", "kind": "robot", "capacity": 60},
                         {"name": "server", "kind": "server", "capacity": 400}],
           "nodes": nodes, "edges": [{"from": "cam", "to": "a", "topic": "/img"}]}
    doc.update(extra)
    return doc


@pytest.mark.parametrize(("container", "message"), [("nope", "unknown node 'nope'"), ("a", "is itself hosted"),
                                                   ("b", "a node cannot host itself")])
def test_container_must_name_a_host(container: str, message: str) -> None:
    doc = _doc()
    doc["nodes"][3]["container"] = container  # type: ignore[index]
    with pytest.raises(InputError, match=message):
        parse_system(doc, "s.yaml")


def test_container_is_coresidence_and_the_checker_refuses_a_split(tmp_path: Path) -> None:
    system = parse_system(_doc(), "s.yaml")
    groups = sorted(sorted(g) for g in system.coresidence_groups)
    assert groups == [["a", "b", "mgr"], ["cam"]]
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(_doc()))
    out = tmp_path / "plan.json"
    done = subprocess.run([str(BIN), "solve", str(tmp_path / "s.yaml"), "--problem", "1", "--method", "exact",
                           "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    plan = load_plan(out)
    where = {n: p.computer for n, p in plan.nodes.items()}
    assert where["a"] == where["b"] == where["mgr"]  # 60 units on the robot cannot hold both: all on the server
    assert check_plan(system, plan) == []
    # move one nodelet away from its manager: the checker and every plan reader refuse it
    raw = json.loads(out.read_text())
    other = "robot" if where["a"] == "server" else "server"
    raw["nodes"]["a"]["computer"] = other
    split = tmp_path / "split.json"
    split.write_text(json.dumps(raw))
    bad = load_plan(split)
    assert any(p.startswith("container: a on") for p in check_plan(system, bad))
    done = subprocess.run([str(BIN), "export", str(split), "--format", "roslaunch", "--system",
                           str(tmp_path / "s.yaml"), "--out", str(tmp_path / "x.launch")],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    lines = [x for x in done.stderr.splitlines() if x.strip()]
    assert len(lines) == 1 and "container mgr" in lines[0] and "split.json" in lines[0], done.stderr
    assert not (tmp_path / "x.launch").exists()


def _opencv_apps_class(lookup: str) -> str:
    """The C++ class of ``lookup`` in Debian's opencv_apps plugin description, read with a
    regular expression (not perfros_bag's reader)."""
    text = Path("/usr/share/opencv_apps/nodelet_plugins.xml").read_text()
    return dict(re.findall(r'<class\s+name="([^"]+)"\s+type="([^"]+)"', text))[lookup]


@pytest.mark.parametrize("kind", ["people_detect", "opencv_apps/people_detect", "opencv_apps::PeopleDetectNodelet"])
def test_ros2_export_writes_a_container_per_computer(tmp_path: Path, kind: str) -> None:
    """Per computer, a ``<node_container>`` with a ``<composable_node>`` per hosted node, the
    element and attribute names of ROS 2's "Launching composable nodes" guide (XML); the
    plugin the C++ class, whichever form ``launch.type`` names it in. The ROS 1 export loads
    the same class by its lookup name into its manager."""
    import xml.etree.ElementTree as ET

    from perfros_bag.export.writers import ros2_launch_path

    doc = _doc()
    doc["nodes"][2]["launch"] = {"package": "opencv_apps", "type": kind}  # type: ignore[index]
    (tmp_path / "s.yaml").write_text(yaml.safe_dump(doc))
    plan = tmp_path / "plan.json"
    done = subprocess.run([str(BIN), "solve", str(tmp_path / "s.yaml"), "--problem", "1", "--method", "exact",
                           "--out", str(plan)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    out = tmp_path / "params.yaml"
    done = subprocess.run([str(BIN), "export", str(plan), "--format", "ros2-params",
                           "--system", str(tmp_path / "s.yaml"),
                           "--out", str(out)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    where = {n: p.computer for n, p in load_plan(plan).nodes.items()}
    hosted = {n["name"]: n["container"] for n in doc["nodes"] if "container" in n}  # type: ignore[index, union-attr]
    seen: dict[str, str] = {}
    for computer in sorted(set(where.values())):
        root = ET.parse(ros2_launch_path(out, computer)).getroot()
        assert root.tag == "launch"
        for el in root:
            if el.tag == "node":
                assert set(el.attrib) >= {"pkg", "exec", "name"}
                seen[el.get("name") or ""] = computer
            elif el.tag == "node_container":
                assert set(el.attrib) == {"pkg", "exec", "name", "namespace"}
                assert (el.get("pkg"), el.get("exec")) == ("rclcpp_components", "component_container")
                seen[el.get("name") or ""] = computer
                members = [c for c in el if c.tag == "composable_node"]
                assert sorted(c.get("name") for c in members) == sorted(m for m, h in hosted.items()
                                                                       if h == el.get("name"))
                for c in members:
                    assert set(c.attrib) >= {"pkg", "plugin", "name"}
                    seen[c.get("name") or ""] = computer
                plugins = {c.get("name"): c.get("plugin") for c in members}
                assert plugins["a"] == _opencv_apps_class("opencv_apps/people_detect")
    assert seen == where  # every node once, on its plan computer, the hosted ones inside their container
    launch = tmp_path / "x.launch"
    done = subprocess.run([str(BIN), "export", str(plan), "--format", "roslaunch", "--system", str(tmp_path / "s.yaml"),
                           "--out", str(launch)], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    nodes = {n.get("name"): n for n in ET.parse(launch).getroot().iter("node")}
    assert (nodes["a"].get("pkg"), nodes["a"].get("type")) == ("nodelet", "nodelet")
    assert (nodes["a"].get("args") or "").split() == ["load", "opencv_apps/people_detect", "/mgr"]
    assert (nodes["mgr"].get("pkg"), nodes["mgr"].get("type"), nodes["mgr"].get("args")) == ("nodelet", "nodelet",
                                                                                           "manager")
    assert nodes["a"].get("machine") == nodes["mgr"].get("machine") == where["mgr"]


def test_a_nodelet_with_only_its_bond_is_a_warning() -> None:
    from perfros_bag.errors import PerfrosWarning
    from perfros_bag.sweep.draft import _warn_members

    doc = _doc()
    doc["nodes"][2]["topics"] = ["/a/out"]  # type: ignore[index]
    system = parse_system(doc, "s.yaml")  # b publishes nothing of its own (only its bond)
    with pytest.warns(PerfrosWarning) as got:
        _warn_members(system, [])
    messages = [str(w.message) for w in got]
    assert messages == ["node b: a nodelet of mgr whose only published topic is its bond: drafted with no topics "
                        "(performance 100, no rate)"]


def test_a_step_the_runs_spread_hides_is_a_warning() -> None:
    # a's step (1 -> 2) is 20 units, b's 0.2: runs repeated with a spread of +-2 units
    design = [(1, 1), (2, 1), (1, 2)] * 3
    spread = [2.0, -2.0, 1.5, -1.5, 0.5, -0.5, 2.0, -2.0, 0.0]
    totals = {f"r{i}": 10 + 20 * (va - 1) + 0.2 * (vb - 1) + spread[i] for i, (va, vb) in enumerate(design)}
    values = {f"r{i}": {"a": va, "b": vb} for i, (va, vb) in enumerate(design)}
    values["alone"] = {"a": 1, "b": 1}
    rows, _ = _rows(totals, values, alone={"alone": {"a": 8.0, "b": 2.0}})
    s = fit_split(rows, "mgr", ["a", "b"], {"alone": ("a", "b")})
    assert s is not None
    assert [n.split(":")[0] for n in s.notes] == ["node b"]
    assert "at value 2" in s.notes[0] and "standard error" in s.notes[0]


# --------------------------------------------------------------------------- pluginlib's reading


def _package(root: Path, name: str, classes: list[tuple[str | None, str]], export: bool = True) -> Path:
    """A ROS package folder as catkin installs one: package.xml exporting a nodelet plugin
    description (``${prefix}/plugins.xml``) with ``classes`` (lookup name or None, C++ type)."""
    folder = root / "src" / name
    folder.mkdir(parents=True)
    tag = '<export><nodelet plugin="${prefix}/plugins.xml"/></export>' if export else "<export/>"
    (folder / "package.xml").write_text(f'<?xml version="1.0"?><package format="2"><name>{name}</name>'
                                        f'<version>1.0.0</version>{tag}</package>')
    body = "".join(f'<class {f"name={n!r} " if n else ""}type="{t}" base_class_type="nodelet::Nodelet"/>'
                   for n, t in classes)
    (folder / "plugins.xml").write_text(f'<class_libraries><library path="lib{name}">{body}</library>'
                                        "</class_libraries>")
    return folder


def test_plugin_classes_read_as_pluginlib_reads_them(tmp_path: Path) -> None:
    from perfros_bag.sweep.plugins import class_problem, exported_classes, package_dir, resolve_class

    folder = _package(tmp_path, "my_pkg", [("my_pkg/blur", "my_pkg::BlurNodelet"), (None, "my_pkg::Edges")])
    _package(tmp_path, "plain", [("plain/x", "plain::X")], export=False)
    env = {"ROS_PACKAGE_PATH": str(tmp_path)}
    assert package_dir("my_pkg", env) == folder
    got = {(c.name, c.type) for c in exported_classes("my_pkg", env=env) or []}
    # a class without name= is looked up by its type (pluginlib's rule)
    assert got == {("my_pkg/blur", "my_pkg::BlurNodelet"), ("my_pkg::Edges", "my_pkg::Edges")}
    assert exported_classes("plain", env=env) == []  # no <export><nodelet plugin=...>
    assert exported_classes("not_here", env={"ROS_PACKAGE_PATH": str(tmp_path), "CMAKE_PREFIX_PATH": ""}) is None
    # a lookup name or the C++ class: the same class
    a, b = resolve_class("my_pkg", "my_pkg/blur", env), resolve_class("my_pkg", "my_pkg::BlurNodelet", env)
    assert not isinstance(a, str) and a == b and a.name == "my_pkg/blur"
    # nodelet load takes only the lookup name
    assert "C++ class name; nodelet load takes its lookup name my_pkg/blur" in str(
        class_problem("my_pkg", "my_pkg::BlurNodelet", env, by_type=False))
    assert "exports no such nodelet (its nodelets: my_pkg/blur)" in str(class_problem("my_pkg", "my_pkg/sharpen", env))
    assert "exports no nodelet" in str(class_problem("plain", "plain/x", env))


def test_plugin_classes_of_the_installed_opencv_apps() -> None:
    """Against Debian's opencv_apps: the description file is the one rospack lists for it,
    and every ``<class name= type=>`` of that file, read here with a regular expression, is
    found both ways."""
    import re

    from perfros_bag.sweep.plugins import exported_classes, resolve_class

    listed = subprocess.run(["rospack", "plugins", "--attrib=plugin", "nodelet"], capture_output=True, text=True,
                            check=True).stdout.split("\n")
    path = next(line.split(None, 1)[1].strip() for line in listed if line.startswith("opencv_apps "))
    pairs = re.findall(r'<class\s+name="([^"]+)"\s+type="([^"]+)"', Path(path).read_text())
    classes = exported_classes("opencv_apps")
    assert classes is not None and {str(c.description) for c in classes} == {path}
    assert sorted((c.name, c.type) for c in classes) == sorted(pairs) and len(pairs) > 20
    for name, kind in pairs:
        if name.startswith("opencv_apps/"):
            by_name, by_type = resolve_class("opencv_apps", name), resolve_class("opencv_apps", kind)
            assert not isinstance(by_name, str) and not isinstance(by_type, str)
            assert by_name.type == kind and by_type.name == name  # the package's own lookup name, not the old alias
    assert resolve_class("opencv_apps", "opencv_apps::PeopleDetectNodelet").name == "opencv_apps/people_detect"  # type: ignore[union-attr]


@pytest.mark.parametrize(("kind", "message"), [
    ("opencv_apps/no_such", "class opencv_apps/no_such does not exist: package opencv_apps exports no such nodelet"),
    ("opencv_apps::SmoothingNodelet", "nodelet load takes its lookup name opencv_apps/smoothing"),
    ("roscpp/x", "package roscpp exports no nodelet"),
    ("no_pkg_here/x", "package no_pkg_here is not installed here")])
def test_unexported_nodelet_type_is_one_error(kind: str, message: str) -> None:
    r = _resolved()
    nodes = tuple(_node("smooth", f"load {kind} vision_manager") if n.name == "smooth" else n for n in r.nodes)
    with pytest.raises(InputError, match=re.escape(message)):
        check_nodelets(Resolved(nodes, {}, {}), "x.launch")
    assert check_nodelets(r, "x.launch")  # the launch file as it is passes


def test_a_plan_splitting_a_launch_files_nodelet_from_its_manager() -> None:
    from perfros_bag.sweep.nodelets import check_plan_membership

    nodelets = nodelets_of(_resolved())
    kept = {"camera": "robot", "vision_manager": "server", "people": "server", "smooth": "server"}
    check_plan_membership(nodelets, kept, "plan.json")
    with pytest.raises(InputError) as got:
        check_plan_membership(nodelets, {**kept, "smooth": "robot"}, "plan.json")
    assert str(got.value).startswith("plan.json: container vision_manager: node smooth on robot but its container "
                                     "vision_manager on server")


def test_residence_that_splits_a_container_names_both_nodes() -> None:
    doc = _doc()
    doc["nodes"][2]["residence"] = ["robot"]  # type: ignore[index]
    doc["nodes"][3]["residence"] = ["server"]  # type: ignore[index]
    with pytest.raises(InputError) as got:
        parse_system(doc, "s.yaml")
    assert str(got.value).startswith("s.yaml: container 'mgr': residence: nodes 'a' (allowed on robot) and 'b' "
                                     "(allowed on server) share the process of container 'mgr'")


def test_plugin_types_in_launch_type() -> None:
    """``launch.type`` as a plugin class: only for a hosted node; resolved per ROS version;
    what cannot be resolved is an error where the other form cannot be guessed."""
    from perfros_bag.errors import PerfrosWarning
    from perfros_bag.sweep.plugins import hosted_plugin

    doc = _doc()
    doc["nodes"][0]["launch"] = {"package": "opencv_apps", "type": "opencv_apps::SmoothingNodelet"}  # type: ignore[index]
    with pytest.raises(InputError, match=r"node 'cam': launch.type: 'opencv_apps::SmoothingNodelet' names a plugin "
                                         r"class, which only a node with a container"):
        parse_system(doc, "s.yaml")
    doc = _doc()
    doc["nodes"][2]["launch"] = {"package": "opencv_apps", "type": "opencv_apps::Smoothing::"}  # type: ignore[index]
    with pytest.raises(InputError, match=r"launch.type: 'opencv_apps::Smoothing::' is not a valid plugin class name"):
        parse_system(doc, "s.yaml")
    smooth = _opencv_apps_class("opencv_apps/smoothing")
    for given in ("smoothing", "opencv_apps/smoothing", smooth, "smoothing/smoothing"):
        assert hosted_plugin("opencv_apps", given, "a", ros2=False) == (
            "smoothing/smoothing" if given == "smoothing/smoothing" else "opencv_apps/smoothing")
        assert hosted_plugin("opencv_apps", given, "a", ros2=True) == _opencv_apps_class(
            "smoothing/smoothing" if given == "smoothing/smoothing" else "opencv_apps/smoothing")
    with pytest.raises(InputError, match=r"s.yaml: node 'a': launch.type 'opencv_apps::NoSuch': cannot tell the "
                                         r"lookup name nodelet load takes: package opencv_apps exports no such"):
        hosted_plugin("opencv_apps", "opencv_apps::NoSuch", "a", ros2=False, source="s.yaml")
    assert hosted_plugin("my_ros2_pkg", "my_ros2_pkg::Talker", "a", ros2=True) == "my_ros2_pkg::Talker"
    with pytest.raises(InputError, match=r"cannot tell the C\+\+ class a ROS 2 composable node names"):
        hosted_plugin("my_ros2_pkg", "my_ros2_pkg/talker", "a", ros2=True)
    with pytest.warns(PerfrosWarning, match=r"node a: launch.type 'my_ros2_pkg/talker' is no nodelet class found here"):
        assert hosted_plugin("my_ros2_pkg", "my_ros2_pkg/talker", "a", ros2=False) == "my_ros2_pkg/talker"


def test_membership_keep_is_explicit() -> None:
    assert parse_system(_doc(), "s.yaml").membership == "keep"  # the default
    system = parse_system(_doc(membership="keep"), "s.yaml")
    assert system.membership == "keep" and sorted(sorted(g) for g in system.coresidence_groups) == [
        ["a", "b", "mgr"], ["cam"]]
    assert parse_system(_doc(membership="choose"), "s.yaml").membership == "choose"  # tests/test_membership_choose.py
    with pytest.raises(InputError, match=r"s.yaml: membership: must be one of keep, choose, got 'maybe'"):
        parse_system(_doc(membership="maybe"), "s.yaml")


# --------------------------------------------------------------------------- the copy price


def _copy_system(**extra: object) -> object:
    doc: dict[str, object] = {
        "computers": [{"name": "c", "kind": "robot", "capacity": 400}],
        "nodes": [{"name": "cam", "weight": 0.25, "topics": ["/img"], "settings": [{"cpu": 1, "performance": 1}]},
                  {"name": "mgr", "weight": 0.25, "settings": [{"cpu": 1, "performance": 1}]},
                  {"name": "a", "weight": 0.25, "container": "mgr", "topics": ["/a/out"],
                   "settings": [{"cpu": 1, "performance": 1}]},
                  {"name": "b", "weight": 0.25, "container": "mgr", "settings": [{"cpu": 1, "performance": 1}]}],
        "edges": [{"from": "cam", "to": "a", "topic": "/img"}, {"from": "cam", "to": "b", "topic": "/img"},
                  {"from": "a", "to": "b", "topic": "/a/out"}]}
    doc.update(extra)
    return parse_system(doc, "s.yaml")


def _copy_row(rec: str, node: str, cpu: float, topic: str | None = None, kbps: float | None = None) -> Row:
    return Row(rec, node, None, None, topic, "t" if topic else None, 10, 10.0, 10.0 if topic else None, kbps, cpu,
               cpu, 20)


def test_copy_price_against_a_hand_computation() -> None:
    """Inside (two repeats): camera 10 / 11, manager 50 / 52, loaders 0.5 each; standalone:
    camera 12, a 30, b 35. Split, the container adds one more copy of /img (2000 kB/s: two
    receivers instead of one process) and one of a -> b (/a/out, 100 kB/s, a pointer
    inside): 2.1 MB/s. Extra CPU 77 - mean(61, 64) = 14.5: 14.5 / 2.1 units per MB/s."""
    from perfros_bag.characterisation.containers import split_containers

    system = _copy_system()
    rows = []
    for rec, cam, mgr in (("r1", 10.0, 50.0), ("r2", 11.0, 52.0)):
        rows += [_copy_row(rec, "cam", cam, "/img", 1990.0), _copy_row(rec, "mgr", mgr),
                 _copy_row(rec, "a", 0.5, "/a/out", 99.0), _copy_row(rec, "b", 0.5)]
    rows += [_copy_row("s", "cam", 12.0, "/img", 2000.0), _copy_row("s", "a", 30.0, "/a/out", 100.0),
             _copy_row("s", "b", 35.0)]
    entries = [RecordingEntry(Path(r), r) for r in ("r1", "r2")] + [RecordingEntry(Path("s"), "s",
                                                                                  standalone=("a", "b"))]
    _, splits = split_containers(rows, system, entries)  # type: ignore[arg-type]
    (s,) = splits
    assert s.copy_runs == {"r1+r2|s": (pytest.approx(14.5), pytest.approx(2100.0))}
    assert s.copy_per_MBps == pytest.approx(14.5 / 2.1)
    # the model carries it on the container, and only there
    assert _copy_system(nodes=[*_copy_doc_nodes(copy=6.9)]).node["mgr"].copy_cpu_per_MBps == 6.9  # type: ignore[attr-defined]
    with pytest.raises(InputError, match=r"node 'a': copy_cpu_per_MBps: only a container"):
        nodes = _copy_doc_nodes()
        nodes[2]["copy_cpu_per_MBps"] = 1.0
        _copy_system(nodes=nodes)


def test_a_negative_copy_price_is_zero_with_a_note() -> None:
    from perfros_bag.characterisation.containers import split_containers

    system = _copy_system()
    rows = [_copy_row("r1", "cam", 10.0, "/img", 2000.0), _copy_row("r1", "mgr", 70.0),
            _copy_row("r1", "a", 0.5, "/a/out", 100.0), _copy_row("r1", "b", 0.5),
            _copy_row("s", "cam", 10.0, "/img", 2000.0), _copy_row("s", "a", 30.0, "/a/out", 100.0),
            _copy_row("s", "b", 35.0)]
    entries = [RecordingEntry(Path("r1"), "r1"), RecordingEntry(Path("s"), "s", standalone=("a", "b"))]
    _, (s,) = split_containers(rows, system, entries)  # type: ignore[arg-type]
    assert s.copy_runs == {"r1|s": (pytest.approx(75.0 - 81.0), pytest.approx(2100.0))}
    assert s.copy_per_MBps == 0.0
    assert any(n.startswith(f"container mgr: its copy price measured {-6.0 / 2.1:.4g} CPU units per MB/s")
               and n.endswith("drafted as 0") for n in s.notes)


def _copy_doc_nodes(copy: float | None = None) -> list[dict[str, object]]:
    nodes: list[dict[str, object]] = [
        {"name": "cam", "weight": 0.25, "topics": ["/img"], "settings": [{"cpu": 1, "performance": 1}]},
        {"name": "mgr", "weight": 0.25, "settings": [{"cpu": 1, "performance": 1}]},
        {"name": "a", "weight": 0.25, "container": "mgr", "topics": ["/a/out"], "settings": [{"cpu": 1,
                                                                                            "performance": 1}]},
        {"name": "b", "weight": 0.25, "container": "mgr", "settings": [{"cpu": 1, "performance": 1}]}]
    if copy is not None:
        nodes[1]["copy_cpu_per_MBps"] = copy
    return nodes


def test_no_copy_price_without_a_copy_to_price() -> None:
    """Two nodes that share no topic and pass nothing: splitting adds no copy: a note, no price."""
    from perfros_bag.characterisation.containers import split_containers

    system = _copy_system(edges=[{"from": "cam", "to": "a", "topic": "/img"}])
    rows = [_copy_row("r1", "cam", 10.0, "/img", 2000.0), _copy_row("r1", "mgr", 50.0), _copy_row("r1", "a", 0.5),
            _copy_row("r1", "b", 0.5), _copy_row("s", "cam", 10.0, "/img", 2000.0), _copy_row("s", "a", 30.0),
            _copy_row("s", "b", 25.0)]
    entries = [RecordingEntry(Path("r1"), "r1"), RecordingEntry(Path("s"), "s", standalone=("a", "b"))]
    _, (s,) = split_containers(rows, system, entries)  # type: ignore[arg-type]
    assert s.copy_per_MBps is None and s.copy_runs == {"r1|s": (pytest.approx(65.0 - 61.0), 0.0)}
    assert any(n.startswith("container mgr: no copy price: its nodes share no topic") for n in s.notes)


def test_a_replan_that_splits_a_nodelet_is_not_applied(tmp_path: Path) -> None:
    """deploy's control file: a new plan that moves a nodelet away from its manager (the
    launch file's membership) is a warning, and nothing is restarted."""
    import os

    from perfros_bag.errors import PerfrosWarning
    from perfros_bag.sweep.control import Control, write_control
    from perfros_bag.sweep.deploy import plan_run
    from perfros_bag.sweep.space import load_space
    from perfros_bag.system.plan import Plan, PlannedComputer, PlannedNode
    from perfros_bag.system.planfile import save_plan
    from tests.conftest import fake_control_run

    def plan(smooth_on: str) -> Plan:
        return Plan(1, "exact", "optimal", computers={"robot": PlannedComputer("robot", 100.0, 10.0),
                                                      "server": PlannedComputer("server", 100.0, 10.0)},
                    nodes={n: PlannedNode(smooth_on if n == "smooth" else ("robot" if n == "camera" else "server"),
                                          5.0, 50.0, 1.0) for n in ("camera", "vision_manager", "people", "smooth")})

    restarter, groups, calls = fake_control_run(tmp_path, ("robot", "server"),
                                                ("camera", "people", "smooth", "vision_manager"))
    where = {n: pn.computer for n, pn in plan("server").nodes.items()}
    space = load_space(Path(__file__).resolve().parents[1] / "fixtures" / "nodelet" / "space.yaml")
    control = Control(tmp_path, space, {}, plan_run(plan("server"), space, {}), where, groups, 100.0, False,
                      nodelets=nodelets_of(_resolved()))
    save_plan(plan("robot"), tmp_path / "split.json")
    write_control(tmp_path, 1, tmp_path / "split.json", ["why"])
    os.utime(tmp_path / "control.json", (1, 1))
    with pytest.warns(PerfrosWarning, match=r"not applied: .*split.json: container vision_manager: node smooth on "
                                            r"robot but its container vision_manager on server"):
        control.tick(restarter)  # type: ignore[arg-type]
    assert calls == [] and control.seq == 0 and control.where == where


@pytest.mark.parametrize(("standalone_run", "bandwidth", "note"), [
    (False, 2000.0, None),  # never standalone: the split says so; no second note
    (True, None, "container mgr: no copy price: an edge into or inside it has no topic, or its topic no measured"),
])
def test_copy_price_notes(standalone_run: bool, bandwidth: float | None, note: str | None) -> None:
    from perfros_bag.characterisation.containers import split_containers

    system = _copy_system()
    rows = [_copy_row("r1", "cam", 10.0, "/img", 2000.0), _copy_row("r1", "mgr", 50.0),
            _copy_row("r1", "a", 0.5, "/a/out", 100.0), _copy_row("r1", "b", 0.5),
            _copy_row("r2", "cam", 10.0, "/img", 2000.0), _copy_row("r2", "mgr", 52.0),
            _copy_row("r2", "a", 0.5, "/a/out", 100.0), _copy_row("r2", "b", 0.5)]
    entries = [RecordingEntry(Path("r1"), "r1"), RecordingEntry(Path("r2"), "r2")]
    if standalone_run:
        rows += [_copy_row("s", "cam", 10.0, "/img", bandwidth), _copy_row("s", "a", 30.0, "/a/out", bandwidth),
                 _copy_row("s", "b", 25.0)]
        entries.append(RecordingEntry(Path("s"), "s", standalone=("a", "b")))
    _, (s,) = split_containers(rows, system, entries)  # type: ignore[arg-type]
    copy_notes = [n for n in s.notes if "copy price" in n]
    assert s.copy_per_MBps is None
    assert copy_notes == [] if note is None else (len(copy_notes) == 1 and copy_notes[0].startswith(note))
    if not standalone_run:
        assert any("never ran standalone" in n for n in s.notes)


def test_export_only_warns_about_a_package_not_installed_here() -> None:
    """``export --launch`` writes a file for other machines: a nodelet package missing here
    is a warning there; sweep and deploy, which run it here, refuse it."""
    from perfros_bag.errors import PerfrosWarning

    r = _resolved()
    nodes = tuple(_node("smooth", "load elsewhere_pkg/blur vision_manager") if n.name == "smooth" else n
                  for n in r.nodes)
    with pytest.warns(PerfrosWarning, match=r"x.launch: node /smooth: class elsewhere_pkg/blur not checked: package "
                                            r"elsewhere_pkg is not installed here"):
        assert sorted(check_nodelets(Resolved(nodes, {}, {}), "x.launch", elsewhere=True)) == ["/people", "/smooth"]
    with pytest.raises(InputError, match="package elsewhere_pkg is not installed here"):
        check_nodelets(Resolved(nodes, {}, {}), "x.launch")


def test_fixture_standalone_launch_mirrors_the_managers_nodelets() -> None:
    """bench_nodelets compares each nodelet inside the manager with itself in
    fixtures/nodelet/standalone.launch: the two files must give every node the same
    arguments, parameters and remappings (but `load TYPE MANAGER` for `standalone TYPE`), and
    declare the same args with the same defaults, read from the XML itself."""
    import xml.etree.ElementTree as ET

    fix = Path(__file__).resolve().parents[1] / "fixtures" / "nodelet"

    def read(name: str) -> tuple[dict[str, str | None], dict[str, tuple]]:
        root = ET.parse(fix / name).getroot()
        args = {a.get("name") or "": a.get("default") for a in root.iter("arg")}
        nodes = {}
        for n in root.iter("node"):
            words = (n.get("args") or "").split()
            if words[:1] == ["load"]:
                words = ["standalone", words[1]]
            nodes[n.get("name") or ""] = (n.get("pkg"), n.get("type"), words,
                                          sorted((p.get("name"), p.get("value")) for p in n.iter("param")),
                                          sorted((r.get("from"), r.get("to")) for r in n.iter("remap")))
        return args, nodes

    args_in, inside = read("nodelet.launch")
    args_alone, alone = read("standalone.launch")
    assert args_in == args_alone and "filter_type" in args_in
    assert set(inside) - set(alone) == {"vision_manager"}  # the manager only inside
    assert {k: v for k, v in inside.items() if k != "vision_manager"} == alone
    space = yaml.safe_load((fix / "space.yaml").read_text())
    assert {v["arg"] for v in space["vary"]} <= set(args_in)
