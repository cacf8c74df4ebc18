"""export: ROS 1 launch XML and ROS 2 parameters from a plan."""

from __future__ import annotations

import json
import shutil
import subprocess
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import pytest
import yaml
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import InfeasibleError, InputError
from perfros_bag.export.writers import (
    export_plan,
    read_placement_comments,
    ros2_params_yaml,
    roslaunch_xml,
)
from perfros_bag.system.planfile import parse_plan
from perfros_bag.system.systemfile import parse_system

TRACKER = "tracker_1"
WEIRD = 'trk&<1> "q\' x'  # XML-special characters: no ROS name, refused (issue 16)

PLAN: dict[str, Any] = {
    "format": "perfros-bag/plan@1", "problem": 1, "method": "test", "status": "optimal",
    "computers": {"robot1": {"kind": "robot", "capacity": 100, "cpu": 60},
                  "server": {"kind": "server", "capacity": 400, "cpu": 200}},
    "links": [],
    "nodes": {
        "amcl": {"computer": "robot1", "parameter": "particles", "value": 500.0, "cpu": 41,
                 "performance": 50, "weight": 0.4, "topics": {}},
        "nav": {"computer": "robot1", "parameter": "controller_frequency", "value": 12.5, "cpu": 19,
                "performance": 70, "weight": 0.3, "topics": {}},
        TRACKER: {"computer": "server", "parameter": "out_freq", "value": 22.0, "cpu": 176,
                "performance": 95, "weight": 0.2, "topics": {}},
        "core": {"computer": "robot1", "parameter": None, "value": None, "cpu": 16,
                 "performance": 100, "weight": 0.1, "topics": {}},
    },
}

SYSTEM: dict[str, Any] = {
    "computers": [{"name": "robot1", "kind": "robot", "capacity": 100},
                  {"name": "server", "kind": "server", "capacity": 400}],
    "machines": {"robot1": {"address": "10.0.0.2", "user": "ro&b\"o<t>'", "env_loader": "/opt/env.sh"}},
    "nodes": [
        {"name": "amcl", "weight": 0.4, "parameter": {"name": "particles", "type": "int"},
         "launch": {"package": "amcl", "type": "amcl", "param": "max_particles", "namespace": "robot1"},
         "settings": [{"value": 200, "cpu": 19, "performance": 20}, {"value": 3000, "cpu": 66, "performance": 100}]},
        {"name": "nav", "weight": 0.3, "parameter": {"name": "controller_frequency"},
         "launch": {"package": "move_base", "type": "move_base", "name": "move_base"},
         "settings": [{"value": 2, "cpu": 25, "performance": 10}, {"value": 20, "cpu": 50, "performance": 100}]},
        {"name": TRACKER, "weight": 0.2, "parameter": {"name": "out_freq", "type": "float"},
         "launch": {"package": "pk-g", "type": "track.py"},
         "settings": [{"value": 10, "cpu": 80, "performance": 40}, {"value": 25, "cpu": 200, "performance": 100}]},
        {"name": "core", "weight": 0.1, "settings": [{"cpu": 16, "performance": 100}]},
    ],
}


def plan() -> Any:
    return parse_plan(json.loads(json.dumps(PLAN)), "plan.json")


def system() -> Any:
    return parse_system(json.loads(json.dumps(SYSTEM)), "system.yaml")


def test_launch_without_system_names_every_node_machine_and_param() -> None:
    root = ET.fromstring(roslaunch_xml(plan()))
    assert root.tag == "launch"
    machines = {m.get("name"): m for m in root.iter("machine")}
    assert set(machines) == {"robot1", "server"}
    args = {a.get("name"): a.get("default") for a in root.iter("arg")}
    assert machines["server"].get("address") == "$(arg server_address)" and args["server_address"] == "server"
    nodes = {n.get("name"): n for n in root.iter("node")}
    assert set(nodes) == set(PLAN["nodes"])
    for name, pn in PLAN["nodes"].items():
        el = nodes[name]
        assert el.get("machine") == pn["computer"]
        params = {p.get("name"): p.get("value") for p in el.iter("param")}
        if pn["value"] is None:
            assert params == {}
        else:
            assert float(params[pn["parameter"]]) == pn["value"]
    # integral values become ints without a system's type, others stay doubles
    assert nodes["amcl"].find("param").attrib == {"name": "particles", "type": "int", "value": "500"}  # type: ignore[union-attr]
    assert nodes["nav"].find("param").get("type") == "double"  # type: ignore[union-attr]


def test_launch_with_system_fields_and_escaping(tmp_path: Path) -> None:
    text = roslaunch_xml(plan(), system())
    assert "&amp;" in text and "&lt;" in text and "&quot;" in text  # escaped, not raw
    root = ET.fromstring(text)
    m = {e.get("name"): e.attrib for e in root.iter("machine")}
    assert m["robot1"] == {"name": "robot1", "address": "10.0.0.2", "user": "ro&b\"o<t>'", "env-loader": "/opt/env.sh"}
    nodes = {n.get("name"): n for n in root.iter("node")}
    assert set(nodes) == {"amcl", "move_base", TRACKER, "core"}
    assert nodes["amcl"].attrib == {"name": "amcl", "pkg": "amcl", "type": "amcl", "machine": "robot1", "ns": "robot1"}
    assert [(p.get("name"), p.get("value"), p.get("type")) for p in nodes["amcl"].iter("param")] == [
        ("max_particles", "500", "int")]
    assert nodes["move_base"].find("param").attrib["value"] == "12.5"  # type: ignore[union-attr]
    tracker = nodes[TRACKER]
    assert (tracker.get("pkg"), tracker.get("type"), tracker.get("machine")) == ("pk-g", "track.py", "server")
    # the system says float: 22.0 stays a double
    assert [(p.get("name"), p.get("value"), p.get("type")) for p in tracker.iter("param")] == [
        ("out_freq", "22.0", "double")]


@pytest.mark.parametrize(("ptype", "value", "written"), [
    (None, 13.0, 13), (None, 13.000000001, 13), (None, 12.5, 12.5),  # no type: as without a system
    ("int", 12.6, 13), ("float", 13.0, 13.0),  # a stated type is kept
])
def test_a_parameter_without_a_type_is_written_as_without_a_system(ptype: str | None, value: float,
                                                                   written: float) -> None:
    """A kernel size the plan holds as 13.0, its system.yaml parameter without ``type``: the
    launch file gets the int 13 (roslaunch's ``type="int"``), the ROS 2 file the YAML int; a
    stated ``type`` decides. Read back with ElementTree and yaml.safe_load."""
    data = json.loads(json.dumps(PLAN))
    data["nodes"][TRACKER]["value"] = value
    sys_data = json.loads(json.dumps(SYSTEM))
    sys_data["nodes"][2]["parameter"] = {"name": "out_freq"} if ptype is None else {"name": "out_freq", "type": ptype}
    p, s = parse_plan(data, "plan.json"), parse_system(sys_data, "system.yaml")
    nodes = {n.get("name"): n for n in ET.fromstring(roslaunch_xml(p, s)).iter("node")}
    (param,) = nodes[TRACKER].iter("param")
    assert param.get("type") == ("int" if isinstance(written, int) else "double")
    assert param.get("value") == str(written) and float(param.get("value") or "nan") == written
    got = yaml.safe_load(ros2_params_yaml(p, s))[TRACKER]["ros__parameters"]["out_freq"]
    assert got == written and type(got) is type(written)


@pytest.mark.parametrize(("field", "value"), [
    ("node", WEIRD), ("node", "nul\x00node"), ("parameter", "out<freq>&"), ("computer", "srv\"><script>"),
    ("computer", "esc\x1bhost"), ("package", 'pk"g&'), ("type", "t<r>ack"),
])
def test_export_refuses_names_ros_cannot_run(tmp_path: Path, field: str, value: str) -> None:
    """A plan-only export checks every name it writes by ROS's rules (issue 16): one line,
    exit 2, the file names the entry and the rule, nothing written."""
    data = json.loads(json.dumps(PLAN))
    system_data = json.loads(json.dumps(SYSTEM))
    if field == "node":
        data["nodes"][value] = data["nodes"].pop("core")
    elif field == "parameter":
        data["nodes"]["core"]["parameter"], data["nodes"]["core"]["value"] = value, 1.0
    elif field == "computer":
        data["computers"][value] = data["computers"].pop("server")
        for n in data["nodes"].values():
            n["computer"] = value if n["computer"] == "server" else n["computer"]
    else:
        system_data["nodes"][2]["launch"][field] = value
    plan_path, sys_path, out = tmp_path / "plan.json", tmp_path / "system.yaml", tmp_path / "x.launch"
    plan_path.write_text(json.dumps(data))
    sys_path.write_text(json.dumps(system_data))
    args = ["export", str(plan_path), "--format", "roslaunch", "--out", str(out)]
    r = CliRunner().invoke(app, args + (["--system", str(sys_path)] if field in ("package", "type") else []))
    assert r.exit_code == 2, r.output
    assert "Traceback" not in r.output and "is not a valid" in r.output
    assert not out.exists()


def test_ros2_params_round_trip() -> None:
    text = ros2_params_yaml(plan(), system())
    data = yaml.safe_load(text)
    assert data == {
        "/robot1/amcl": {"ros__parameters": {"max_particles": 500}},
        "move_base": {"ros__parameters": {"controller_frequency": 12.5}},
        TRACKER: {"ros__parameters": {"out_freq": 22.0}},
        "core": {"ros__parameters": {}},
    }
    assert isinstance(data["/robot1/amcl"]["ros__parameters"]["max_particles"], int)
    assert read_placement_comments(text) == {"/robot1/amcl": "robot1", "move_base": "robot1",
                                             TRACKER: "server", "core": "robot1"}


def test_newline_in_name_cannot_break_the_comment_table(tmp_path: Path) -> None:
    data = json.loads(json.dumps(PLAN))
    data["nodes"]["evil\nkey: 1"] = data["nodes"].pop("core")
    plan_path = tmp_path / "p.json"
    plan_path.write_text(json.dumps(data))
    with pytest.raises(InputError, match="control character"):
        export_plan(plan_path, "ros2-params", tmp_path / "params.yaml")
    assert not (tmp_path / "params.yaml").exists()


def test_infeasible_plan_is_refused() -> None:
    p = parse_plan({"format": "perfros-bag/plan@1", "problem": 2, "method": "x", "status": "infeasible",
                    "reason": "too big"}, "p.json")
    for write in (roslaunch_xml, ros2_params_yaml):
        with pytest.raises(InfeasibleError) as caught:
            write(p, plan_path="p.json")
        assert str(caught.value) == "p.json: infeasible: too big (nothing to export)"


def test_cli_writes_files_atomically(tmp_path: Path) -> None:
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(PLAN))
    sys_path = tmp_path / "system.yaml"
    sys_path.write_text(yaml.safe_dump(SYSTEM))
    runner = CliRunner()
    out = tmp_path / "sys.launch"
    r = runner.invoke(app, ["export", str(plan_path), "--format", "roslaunch", "--out", str(out),
                            "--system", str(sys_path)])
    assert r.exit_code == 0, r.output
    assert {n.get("machine") for n in ET.parse(out).getroot().iter("node")} == {"robot1", "server"}
    out2 = tmp_path / "params.yaml"
    r = runner.invoke(app, ["export", str(plan_path), "--format", "ros2-params", "--out", str(out2)])
    assert r.exit_code == 0, r.output
    assert set(yaml.safe_load(out2.read_text())) == set(PLAN["nodes"])
    # bad input: exit 2, one line, nothing written
    bad = tmp_path / "bad.launch"
    r = runner.invoke(app, ["export", str(tmp_path / "nope.json"), "--format", "roslaunch", "--out", str(bad)])
    assert r.exit_code == 2 and "nope.json" in r.output and "Traceback" not in r.output
    r = runner.invoke(app, ["export", str(plan_path), "--format", "bogus", "--out", str(bad)])
    assert r.exit_code == 2 and "bogus" in r.output
    assert not bad.exists()
    assert [p.name for p in tmp_path.iterdir() if p.name.startswith(".")] == []


# Debian's roslaunch loader on a launch file (argv: the file, then name:=value args): each
# node's machine, each parameter, each machine's address
LOADER = (
    "import sys, roslaunch.config, roslaunch.xmlloader\n"
    "cfg = roslaunch.config.ROSLaunchConfig()\n"
    "roslaunch.xmlloader.XmlLoader().load(sys.argv[1], cfg, argv=['roslaunch'] + sys.argv[2:], verbose=False)\n"
    "for n in cfg.nodes: print('node', n.name, n.machine_name or '')\n"
    "for n in cfg.nodes: print('fullnode', n.namespace.rstrip('/') + '/' + n.name, n.machine_name or '')\n"
    "for k, v in sorted(cfg.params.items()): print('param', k, repr(v.value))\n"
    "for k, m in sorted(cfg.machines.items()): print('machine', k, m.address)\n"
    "for c in sorted(cfg.clear_params): print('clear', c)\n"
)


@pytest.mark.ros
def test_roslaunch_loads_the_file(tmp_path: Path) -> None:
    """Debian's roslaunch parses the exported file: machines and params resolved."""
    if shutil.which("roslaunch") is None or not Path("/usr/bin/python3").exists():
        pytest.fail("Debian ROS 1 (roslaunch) is not installed: run make setup-debs")
    data = json.loads(json.dumps(PLAN))
    data["nodes"]["tracker"] = data["nodes"].pop(TRACKER)
    data["nodes"]["tracker"]["parameter"] = "output_freq"
    path = tmp_path / "sys.launch"
    path.write_text(roslaunch_xml(parse_plan(data, "p.json")))
    r = subprocess.run(["/usr/bin/python3", "-c", LOADER, str(path)], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0, r.stderr
    lines = set(r.stdout.splitlines())
    for name, pn in data["nodes"].items():
        assert f"node {name} {pn['computer']}" in lines
    assert "param /amcl/particles 500" in lines
    assert "param /nav/controller_frequency 12.5" in lines
    assert "param /tracker/output_freq 22" in lines  # integral, no system type: int
    assert "machine server server" in lines


def test_bisection_noise_is_rounded() -> None:
    data = json.loads(json.dumps(PLAN))
    data["nodes"]["nav"]["value"] = 24.99999999301508
    data["nodes"]["amcl"]["value"] = 0.1 + 0.2  # 0.30000000000000004
    nodes = {n.get("name"): n for n in ET.fromstring(roslaunch_xml(parse_plan(data, "p.json"))).iter("node")}
    assert nodes["nav"].find("param").attrib["value"] == "25"  # type: ignore[union-attr]
    assert nodes["amcl"].find("param").attrib["value"] == "0.3"  # type: ignore[union-attr]


def _ros2_inferred(text: str) -> int | float | str:
    """A ROS 2 XML launch ``<param value=>`` as the ROS 2 launch documentation's type inference
    rules read it ("Migrating Launch Files": ``"1"`` an integer, ``"1.0"`` a float, ``"asd"``
    and ``"'1'"`` strings)."""
    import re

    if re.fullmatch(r"[+-]?\d+", text):
        return int(text)
    if re.fullmatch(r"[+-]?(\d+\.\d*|\.\d+)([eE][+-]?\d+)?", text):
        return float(text)
    return text[1:-1] if len(text) >= 2 and text[0] == text[-1] == "'" else text


def test_ros2_launch_file_per_computer_in_the_documented_format(tmp_path: Path) -> None:
    """``ros2-params`` writes, beside the parameters file, one ROS 2 XML launch file per
    computer. No ROS 2 runtime here: each is parsed against the format the ROS 2 launch
    documentation gives (``<launch><node pkg= exec= name= namespace=><param name= value=/>``;
    no ``type``, no ``machine``), its values read by the documented inference rules."""
    plan_path, sys_path = tmp_path / "plan.json", tmp_path / "system.yaml"
    plan_path.write_text(json.dumps(PLAN))
    sys_path.write_text(json.dumps(SYSTEM))
    out = tmp_path / "params.yaml"
    r = CliRunner().invoke(app, ["export", str(plan_path), "--format", "ros2-params", "--out", str(out),
                                 "--system", str(sys_path)])
    assert r.exit_code == 0, r.output
    written = sorted(p.name for p in tmp_path.iterdir())
    assert written == ["params.robot1.launch.xml", "params.server.launch.xml", "params.yaml", "plan.json",
                       "system.yaml"]
    launch_nodes = {n["name"]: n.get("launch", {}) for n in SYSTEM["nodes"]}
    typed = {n["name"]: n.get("parameter", {}).get("type") for n in SYSTEM["nodes"]}
    seen: dict[str, str] = {}
    for computer in ("robot1", "server"):
        root = ET.parse(tmp_path / f"params.{computer}.launch.xml").getroot()
        assert root.tag == "launch" and root.attrib == {}
        for node in root:
            assert node.tag == "node"
            assert {"pkg", "exec"} <= set(node.attrib) <= {"pkg", "exec", "name", "namespace"}
            name = next(n for n, ln in launch_nodes.items() if ln.get("name", n) == node.get("name"))
            ln = launch_nodes[name]
            assert (node.get("pkg"), node.get("exec")) == (ln.get("package", "PACKAGE"), ln.get("type", name))
            assert node.get("namespace") == ln.get("namespace")
            seen[name] = computer
            params = {}
            for p in node:
                assert p.tag == "param" and set(p.attrib) == {"name", "value"}
                params[p.get("name")] = _ros2_inferred(p.get("value", ""))
            pn = PLAN["nodes"][name]
            if pn["value"] is None:
                assert params == {}
                continue
            [(pname, value)] = params.items()
            assert pname == ln.get("param", pn["parameter"])
            assert value == pn["value"]
            assert type(value) is (int if typed[name] == "int" else float)  # the system's type, as ROS 2 infers it
    assert seen == {n: pn["computer"] for n, pn in PLAN["nodes"].items()}


@pytest.mark.parametrize("value", [0.00001, 1e20, -2.5, 3.0, 7, -4, 123456789.125])
def test_ros2_values_keep_their_type_under_the_documented_inference(value: float) -> None:
    from perfros_bag.export.writers import ros2_value

    text = ros2_value(value)
    assert _ros2_inferred(text) == value and type(_ros2_inferred(text)) is type(value), text


def test_names_in_comments_keep_the_xml_well_formed(tmp_path: Path) -> None:
    """A computer name may hold "--", which XML comments cannot: every file still parses."""
    data = json.loads(json.dumps(PLAN))
    data["computers"]["robot--1"] = data["computers"].pop("robot1")
    for n in data["nodes"].values():
        n["computer"] = "robot--1" if n["computer"] == "robot1" else n["computer"]
    plan_path = tmp_path / "plan.json"
    plan_path.write_text(json.dumps(data))
    export_plan(plan_path, "ros2-params", tmp_path / "params.yaml")
    root = ET.parse(tmp_path / "params.robot--1.launch.xml",
                    ET.XMLParser(target=ET.TreeBuilder(insert_comments=True))).getroot()
    assert {n.get("name") for n in root.iter("node")} == {"amcl", "nav", "core"}
    assert any("robot- -1" in (c.text or "") for c in root.iter(ET.Comment))
    export_plan(plan_path, "roslaunch", tmp_path / "system.launch")
    assert {m.get("name") for m in ET.parse(tmp_path / "system.launch").getroot().iter("machine")} == {
        "robot--1", "server"}
