"""ROS names (issue 16): names built by ROS's rules are accepted, mutations of them refused
with the rule named, against Debian's rosgraph where it decides the same question, and
system.yaml / manifest.yaml refuse them naming the file and the entry."""

from __future__ import annotations

import json
import random
import shutil
import subprocess
import warnings
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.characterisation.manifest import parse_manifest
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.system.names import NameKind, address_problem, name_problem, ros2_problem, rule
from perfros_bag.system.systemfile import parse_system

# -- generators following the documented rules (http://wiki.ros.org/Names, design.ros2.org)

TOKEN = st.from_regex(r"[A-Za-z][A-Za-z0-9]{0,8}(_[A-Za-z0-9]{1,5}){0,2}", fullmatch=True)
NODE = st.from_regex(r"[A-Za-z][A-Za-z0-9_]{0,30}", fullmatch=True)
GRAPH = st.builds(lambda lead, tokens: lead + "/".join(tokens), st.sampled_from(["", "/", "~/"]),
                  st.lists(TOKEN, min_size=1, max_size=4))
LABEL = st.from_regex(r"[A-Za-z0-9]([A-Za-z0-9_-]{0,12}[A-Za-z0-9])?", fullmatch=True)
GRAPH_NODE = st.builds(lambda lead, tokens: lead + "/".join(tokens), st.sampled_from(["", "/"]),
                       st.lists(TOKEN, min_size=1, max_size=4))
COMPUTER = st.lists(LABEL, min_size=1, max_size=3).map(".".join)
PACKAGE = st.from_regex(r"[A-Za-z][A-Za-z0-9_-]{0,20}", fullmatch=True)
EXECUTABLE = st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.+-]{0,20}", fullmatch=True)
IDENT = st.from_regex(r"[A-Za-z_][A-Za-z0-9_]{0,12}", fullmatch=True)
PLUGIN = st.one_of(st.lists(IDENT, min_size=2, max_size=4).map("::".join),
                   st.tuples(PACKAGE, EXECUTABLE).map("/".join))
VALID = {NameKind.NODE: NODE, NameKind.TOPIC: GRAPH, NameKind.PARAMETER: GRAPH, NameKind.NAMESPACE: GRAPH,
         NameKind.GRAPH_NODE: GRAPH_NODE, NameKind.COMPUTER: COMPUTER, NameKind.PACKAGE: PACKAGE,
         NameKind.EXECUTABLE: EXECUTABLE, NameKind.PLUGIN: PLUGIN}
#: characters no rule allows anywhere (XML specials, spaces, controls, non-ASCII)
FORBIDDEN = st.sampled_from(list('"<>&\' \t\n\x00\x1b\x7f;:!?*$()[]{}|\\,=@#%^`é→'))


@pytest.mark.parametrize("kind", list(NameKind))
@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_names_by_the_rules_are_accepted(kind: NameKind, data: st.DataObject) -> None:
    name = data.draw(VALID[kind])
    assert name_problem(kind, name) is None, name
    assert ros2_problem(kind, name) is None, name  # the generators follow ROS 2's stricter rules too


@pytest.mark.parametrize("kind", list(NameKind))
@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_a_forbidden_character_anywhere_is_refused_with_the_rule(kind: NameKind, data: st.DataObject) -> None:
    name = data.draw(VALID[kind])
    at = data.draw(st.integers(0, len(name)))
    bad = data.draw(FORBIDDEN)
    mutated = name[:at] + bad + name[at:]
    problem = name_problem(kind, mutated)
    assert problem is not None, mutated
    assert str(kind) in problem
    assert rule(kind) in problem or "control character" in problem


@pytest.mark.parametrize(("kind", "name"), [
    (NameKind.NODE, "1node"), (NameKind.NODE, "_node"), (NameKind.NODE, "a/b"), (NameKind.NODE, "~a"),
    (NameKind.NODE, ""), (NameKind.NODE, "a" * 256),
    (NameKind.TOPIC, "1topic"), (NameKind.TOPIC, "/a//b"), (NameKind.TOPIC, "a~b"), (NameKind.TOPIC, "_a"),
    (NameKind.COMPUTER, "-host"), (NameKind.COMPUTER, "host-"), (NameKind.COMPUTER, "a..b"),
    (NameKind.COMPUTER, "a" * 64), (NameKind.COMPUTER, ".host"),
    (NameKind.PACKAGE, "1pkg"), (NameKind.EXECUTABLE, ".hidden"), (NameKind.EXECUTABLE, "a/b"),
    (NameKind.PLUGIN, "pkg"), (NameKind.PLUGIN, "a:b"), (NameKind.PLUGIN, "a:::b"), (NameKind.PLUGIN, "::a"),
    (NameKind.PLUGIN, "a::1b"), (NameKind.PLUGIN, "a/b/c"), (NameKind.PLUGIN, "a::b/c"),
])
def test_structural_mutations_are_refused(kind: NameKind, name: str) -> None:
    assert name_problem(kind, name) is not None


@pytest.mark.parametrize(("name", "broken"), [
    ("/a/", "ends with '/'"), ("/a__b", "holds '__'"), ("~a", "'~' must be followed by '/'"),
    ("/a/2b", "starts with a digit"),
])
def test_valid_in_ros1_only_is_a_ros2_problem(name: str, broken: str) -> None:
    assert name_problem(NameKind.TOPIC, name) is None
    problem = ros2_problem(NameKind.TOPIC, name)
    assert problem is not None and broken in problem


def test_addresses() -> None:
    for ok in ("10.0.0.2", "::1", "robot1.lab", "$(arg robot_ip)", "$(env ROBOT)", "$(optenv ROBOT)"):
        assert address_problem(ok) is None, ok
    for bad in ('srv"><script>', "a b", "$(eval 1+1)", "host_name", "x\x00"):
        assert address_problem(bad) is not None, bad


@pytest.mark.ros
def test_ros1_rules_agree_with_debians_rosgraph() -> None:
    """For ASCII names rosgraph.names.is_legal_name / is_legal_base_name decide exactly what
    our ROS 1 graph rule / node rule decide (rosgraph also takes "" and non-ASCII letters,
    left out here)."""
    if shutil.which("roslaunch") is None or not Path("/usr/bin/python3").exists():
        pytest.fail("Debian ROS 1 (rosgraph) is not installed: run make setup-debs")
    rng = random.Random(16)
    alphabet = "aZ09_/~-.<\" \t"
    sample = sorted({"".join(rng.choice(alphabet) for _ in range(rng.randint(1, 6))) for _ in range(3000)}
                    | {"/a//b", "a/", "~a", "~/a", "a~", "/", "~", "1a", "/tracker1/out", "robot1.lab"})
    script = ("import json, sys, rosgraph.names as n\n"
              "names = json.load(sys.stdin)\n"
              "print(json.dumps([[n.is_legal_name(x), n.is_legal_base_name(x)] for x in names]))\n")
    r = subprocess.run(["/usr/bin/python3", "-c", script], input=json.dumps(sample), capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    for name, (legal, base) in zip(sample, json.loads(r.stdout), strict=True):
        assert (name_problem(NameKind.TOPIC, name) is None) == legal, name
        assert (name_problem(NameKind.NODE, name) is None) == base, name


# -- the files that carry names

SYSTEM: dict[str, Any] = {
    "computers": [{"name": "robot1", "kind": "robot", "capacity": 100},
                  {"name": "server", "kind": "server", "capacity": 400}],
    "machines": {"robot1": {"address": "10.0.0.2", "user": "ros"}},
    "nodes": [
        {"name": "tracker", "weight": 0.5, "parameter": {"name": "rate"}, "topics": ["/tracker/out"],
         "launch": {"package": "pkg", "type": "tracker.py", "name": "tracker", "namespace": "/robot1",
                    "param": "rate"},
         "settings": [{"value": 1, "cpu": 10, "performance": 10, "topics": {"/tracker/out": {"frequency_hz": 1}}},
                      {"value": 2, "cpu": 20, "performance": 20}]},
        {"name": "sink", "weight": 0.5, "settings": [{"cpu": 1, "performance": 100}]},
    ],
    "edges": [{"from": "tracker", "to": "sink", "topic": "/tracker/out"}],
}

HOSTILE = {
    "node": 'a"><include file="/etc/passwd"/><x y="',
    "topic": "/t<script>",
    "computer": 'srv"><script>alert(1)</script>',
    "nul": "tra\x00cker",
    "esc": "tra\x1bcker",
}


def _mutations() -> list[tuple[str, Any, str]]:
    """(label, mutate(system), text the error must contain)."""
    def setter(*path: Any, value: Any) -> Any:
        def mutate(d: dict[str, Any]) -> None:
            target: Any = d
            for key in path[:-1]:
                target = target[key]
            target[path[-1]] = value
        return mutate

    def rename_computer(value: str) -> Any:
        def mutate(d: dict[str, Any]) -> None:
            d["computers"][1]["name"] = value
        return mutate

    def topic_key(d: dict[str, Any]) -> None:
        d["nodes"][0]["settings"][0]["topics"] = {HOSTILE["topic"]: {"frequency_hz": 1}}

    return [
        ("node name", setter("nodes", 0, "name", value=HOSTILE["node"]), "nodes[0].name"),
        ("node NUL", setter("nodes", 1, "name", value=HOSTILE["nul"]), "control character"),
        ("node ESC", setter("nodes", 1, "name", value=HOSTILE["esc"]), "control character"),
        ("topic", setter("nodes", 0, "topics", 0, value=HOSTILE["topic"]), "topics[0]"),
        ("setting topic", topic_key, "settings[0].topics"),
        ("edge topic", setter("edges", 0, "topic", value=HOSTILE["topic"]), "edges[0].topic"),
        ("parameter", setter("nodes", 0, "parameter", "name", value="rate&x"), "parameter.name"),
        ("computer", rename_computer(HOSTILE["computer"]), "computers[1].name"),
        ("launch.package", setter("nodes", 0, "launch", "package", value="pk\x00g"), "launch.package"),
        ("launch.type", setter("nodes", 0, "launch", "type", value="t<r>ack"), "launch.type"),
        ("launch.name", setter("nodes", 0, "launch", "name", value="a/b"), "launch.name"),
        ("launch.namespace", setter("nodes", 0, "launch", "namespace", value="/ns//x"), "launch.namespace"),
        ("launch.param", setter("nodes", 0, "launch", "param", value="p q"), "launch.param"),
        ("machine address", setter("machines", "robot1", "address", value='10.0.0.2"><x'), "machines.robot1.address"),
        ("machine user", setter("machines", "robot1", "user", value="ro\x1bs"), "machines.robot1.user"),
    ]


@pytest.mark.parametrize(("label", "mutate", "where"), _mutations(), ids=[m[0] for m in _mutations()])
def test_system_yaml_refuses_names_naming_file_entry_and_rule(label: str, mutate: Any, where: str) -> None:
    with warnings.catch_warnings():
        warnings.simplefilter("error", PerfrosWarning)
        parse_system(json.loads(json.dumps(SYSTEM)), "system.yaml")  # the base is valid, no warning
    data = json.loads(json.dumps(SYSTEM))
    mutate(data)
    with pytest.raises(InputError) as caught:
        parse_system(data, "system.yaml")
    message = str(caught.value)
    assert message.startswith("system.yaml: ") and where in message, message
    assert "\n" not in message.replace("\\n", "")


def test_ros1_only_topic_is_kept_with_a_warning() -> None:
    data = json.loads(json.dumps(SYSTEM))
    data["nodes"][0]["topics"] = ["/tracker__out"]
    with pytest.warns(PerfrosWarning, match="not a ROS 2 one"):
        system = parse_system(data, "system.yaml")
    assert system.node["tracker"].topics == ("/tracker__out",)


def test_system_yaml_file_with_hostile_node_is_one_line_exit_2(tmp_path: Path) -> None:
    from typer.testing import CliRunner

    from perfros_bag.cli import app

    data = json.loads(json.dumps(SYSTEM))
    data["nodes"][0]["name"] = HOSTILE["node"]
    path = tmp_path / "system.yaml"
    path.write_text(yaml.safe_dump(data))
    r = CliRunner().invoke(app, ["solve", str(path)])
    assert r.exit_code == 2
    lines = [ln for ln in r.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"error: {path}: nodes[0].name:"), r.stderr
    assert "node name" in lines[0]


@pytest.mark.parametrize(("entry", "where"), [
    ({"path": "a.bag", "computer": HOSTILE["computer"]}, "recordings[0].computer"),
    ({"path": "a.bag", "settings": {HOSTILE["node"]: 1}}, "recordings[0].settings"),
    ({"path": "a.bag", "settings": {"trk\x00": 1}}, "control character"),
])
def test_manifest_refuses_names(tmp_path: Path, entry: dict[str, Any], where: str) -> None:
    with pytest.raises(InputError) as caught:
        parse_manifest({"recordings": [entry]}, tmp_path / "manifest.yaml")
    assert where in str(caught.value)


def test_a_launched_node_gets_a_valid_system_name() -> None:
    from perfros_bag.system.names import system_node_name

    assert system_node_name("/robot1/amcl") == "robot1_amcl"
    assert system_node_name("/camera") == "camera"
    for ros_name in ("/robot1/amcl", "/a/b/c_d", "camera"):
        assert name_problem(NameKind.GRAPH_NODE, ros_name) is None
        assert name_problem(NameKind.NODE, system_node_name(ros_name)) is None
    assert name_problem(NameKind.GRAPH_NODE, "/camera/") is not None
    assert name_problem(NameKind.GRAPH_NODE, "my camera") is not None
