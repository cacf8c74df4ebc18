"""space.yaml: every bad field is one InputError naming the file and the field; the runs of
both designs; the launch file's <arg>s checked before anything starts."""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.errors import InputError
from perfros_bag.sweep.launchfile import check_space, read_launch
from perfros_bag.sweep.space import Design, load_space, plan_runs
from tests.conftest import FIXTURES

APP = FIXTURES / "app" / "app.launch"

GOOD: dict[str, Any] = {
    "duration_s": 4, "settle_s": 1, "repeats": 1, "design": "grid",
    "vary": [
        {"node": "camera", "parameter": {"name": "publish_rate", "unit": "Hz"}, "arg": "camera_rate",
         "values": [5, 10]},
        {"node": "/detector", "parameter": {"name": "canny_threshold"}, "arg": "canny_threshold",
         "values": [100, 200, 300]},
    ],
}


def _write(tmp_path: Path, doc: Any) -> Path:
    p = tmp_path / "space.yaml"
    p.write_text(doc if isinstance(doc, str) else yaml.safe_dump(doc))
    return p


def _with(path: list[Any], value: Any) -> dict[str, Any]:
    doc = yaml.safe_load(yaml.safe_dump(GOOD))
    target = doc
    for key in path[:-1]:
        target = target[key]
    if value is _DROP:
        del target[path[-1]]
    else:
        target[path[-1]] = value
    return doc


_DROP = object()

BAD = [
    ("empty file", "", "empty"),
    ("not a mapping", "[1, 2]", "expected a mapping"),
    ("unknown top key", _with(["durations"], 3), "unknown key(s) 'durations'"),
    ("duration zero", _with(["duration_s"], 0), "duration_s: must be a number > 0"),
    ("duration text", _with(["duration_s"], "long"), "duration_s: must be a number"),
    ("settle negative", _with(["settle_s"], -1), "settle_s: must be a number >= 0"),
    ("repeats zero", _with(["repeats"], 0), "repeats: must be a whole number >= 1"),
    ("repeats float", _with(["repeats"], 1.5), "repeats: must be a whole number >= 1"),
    ("design unknown", _with(["design"], "random"), "design: must be 'one-at-a-time' or 'grid'"),
    ("no vary", _with(["vary"], _DROP), "missing 'vary:'"),
    ("vary empty", _with(["vary"], []), "vary: must be a non-empty list"),
    ("vary item not mapping", _with(["vary", 0], "camera"), "vary[0]: expected a mapping"),
    ("vary unknown key", _with(["vary", 0, "rate"], 3), "vary[0]: unknown key(s) 'rate'"),
    ("node missing", _with(["vary", 0, "node"], _DROP), "vary[0].node: None is not a valid ROS node graph name"),
    ("node bad", _with(["vary", 0, "node"], "my camera"),
     "vary[0].node: 'my camera' is not a valid ROS node graph name"),
    ("parameter missing", _with(["vary", 0, "parameter"], _DROP), "vary[0] (node /camera).parameter: must be"),
    ("parameter unknown key", _with(["vary", 0, "parameter", "type"], "int"), ".parameter: unknown key(s) 'type'"),
    ("neither arg nor param", _with(["vary", 0, "arg"], _DROP), "needs exactly one of 'arg'"),
    ("both arg and param", _with(["vary", 0, "param"], "rate"), "needs exactly one of 'arg'"),
    ("arg bad", _with(["vary", 0, "arg"], "camera rate"), ".arg: must be a roslaunch arg name"),
    ("values missing", _with(["vary", 0, "values"], _DROP), ".values: must be a non-empty list"),
    ("values empty", _with(["vary", 0, "values"], []), ".values: must be a non-empty list"),
    ("values mixed", _with(["vary", 0, "values"], [5, "fast"]), ".values: mixes numbers and strings"),
    ("values bool", _with(["vary", 0, "values"], [True, False]), ".values: must be numbers or strings"),
    ("values nested", _with(["vary", 0, "values"], [[1]]), ".values: must be numbers or strings"),
    ("values twice", _with(["vary", 0, "values"], [5, 5.0]), ".values: lists a value twice"),
    ("default wrong type", _with(["vary", 0, "default"], "slow"), ".default: must be of the same type"),
    ("node twice", _with(["vary", 1, "node"], "/camera"), "node /camera is listed twice"),
    ("arg twice", _with(["vary", 1, "arg"], "camera_rate"), "arg 'camera_rate' is set by two entries"),
    ("exclude not a string", _with(["exclude"], ["/a"]), "exclude: must be a regular expression"),
    ("exclude bad regex", _with(["exclude"], "/camera/(image"), "exclude: not a regular expression"),
]


@pytest.mark.parametrize(("case", "doc", "expected"), BAD, ids=[b[0] for b in BAD])
def test_bad_space_is_one_line_naming_the_file_and_field(tmp_path: Path, case: str, doc: Any, expected: str) -> None:
    path = _write(tmp_path, doc)
    with pytest.raises(InputError) as info:
        load_space(path)
    message = str(info.value)
    assert message.startswith(f"{path}: "), message
    assert expected in message, message
    assert "\n" not in message


def test_missing_space_file_names_it(tmp_path: Path) -> None:
    with pytest.raises(InputError, match="space.yaml: YAML file not found"):
        load_space(tmp_path / "space.yaml")


def test_grid_is_every_combination_in_order(tmp_path: Path) -> None:
    space = load_space(_write(tmp_path, GOOD))
    assert space.design is Design.GRID and space.vary[1].node == "/detector"
    runs = plan_runs(space, {})
    expected = list(itertools.product([5, 10], [100, 200, 300]))
    assert [(r.values["camera"], r.values["detector"]) for r in runs] == expected
    assert [dict(r.args) for r in runs] == [{"camera_rate": str(c), "canny_threshold": str(d)} for c, d in expected]
    assert len({r.name for r in runs}) == len(runs)


def test_one_at_a_time_holds_the_others_at_the_launch_defaults(tmp_path: Path) -> None:
    doc = _with(["design"], "one-at-a-time")
    doc["repeats"] = 2
    space = load_space(_write(tmp_path, doc))
    launch = read_launch(FIXTURES / "app" / "app.launch")
    defaults = {"camera": 10, "detector": 200}  # the <arg> defaults of app.launch
    assert launch.args["camera_rate"] == "10" and launch.args["canny_threshold"] == "200"
    runs = plan_runs(space, launch.args)
    settings = [(r.values["camera"], r.values["detector"]) for r in runs]
    # camera varied with the detector at its default, then the detector with the camera at its
    # default; (10, 200) is both and runs once; every setting twice (repeats)
    once = [(c, defaults["detector"]) for c in (5, 10)] + [(defaults["camera"], d) for d in (100, 300)]
    assert settings == [s for s in once for _ in range(2)]
    assert [r.repeat for r in runs] == [1, 2] * len(once)
    assert len({r.name for r in runs}) == len(runs)


def test_explicit_default_and_param_entries(tmp_path: Path) -> None:
    doc = _with(["design"], "one-at-a-time")
    doc["vary"][0]["default"] = 7
    doc["vary"][1] = {"node": "detector", "parameter": {"name": "canny_threshold"}, "param": "canny_threshold",
                      "values": [100, 200]}
    space = load_space(_write(tmp_path, doc))
    assert space.vary[1].param == "/detector/canny_threshold"  # a relative name is the node's private one
    runs = plan_runs(space, {"camera_rate": "10"})
    assert [(r.values["camera"], r.values["detector"]) for r in runs] == [(5, 100), (10, 100), (7, 100), (7, 200)]
    assert all(dict(r.params) == {"/detector/canny_threshold": r.values["detector"]} for r in runs)
    assert all(dict(r.args) == {"camera_rate": str(r.values["camera"])} for r in runs)


def test_an_undeclared_arg_is_an_error_before_anything_runs(tmp_path: Path) -> None:
    space = load_space(_write(tmp_path, _with(["vary", 1, "arg"], "threshold")))
    launch = read_launch(FIXTURES / "app" / "app.launch")
    with pytest.raises(InputError, match=r"arg 'threshold' is not declared in .*app.launch "
                                         r"\(its <arg>s: camera_rate, canny_threshold, image\)"):
        check_space(launch, space)


def test_included_and_fixed_args(tmp_path: Path) -> None:
    launch = tmp_path / "a.launch"
    launch.write_text('<launch><arg name="fixed" value="1"/><arg name="free"/>'
                      '<group><arg name="inner" default="2"/></group>'
                      '<include file="x.launch"><arg name="passed" value="3"/></include></launch>')
    info = read_launch(launch)
    assert dict(info.args) == {"free": None, "inner": "2"} and info.fixed == {"fixed"}
    space = load_space(_write(tmp_path, _with(["vary", 0, "arg"], "fixed")))
    with pytest.raises(InputError, match="arg 'fixed' has a fixed value="):
        check_space(info, space)


@pytest.mark.parametrize(("text", "expected"), [
    (None, "launch file not found"),
    ("<launch><node", "not a launch file: invalid XML"),
    ("<robot/>", "root element is <robot>"),
])
def test_bad_launch_files(tmp_path: Path, text: str | None, expected: str) -> None:
    path = tmp_path / "app.launch"
    if text is not None:
        path.write_text(text)
    with pytest.raises(InputError, match=expected) as info:
        read_launch(path)
    assert str(info.value).startswith(str(path))


@pytest.mark.ros
@pytest.mark.parametrize("verb", ["sweep", "deploy"])
def test_a_disk_too_full_for_rosbag_is_one_line_before_anything_starts(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, verb: str) -> None:
    """rosbag record stops recording below 1 GiB free (its --min-space default): say so up
    front instead of failing mid-run. The disk's free space is faked at 600 kB."""
    import collections
    import shutil

    import psutil

    from perfros_bag.sweep.deploy import deploy
    from perfros_bag.sweep.runner import sweep

    usage = collections.namedtuple("usage", "total used free")
    monkeypatch.setattr(shutil, "disk_usage", lambda _p: usage(10**6, 4 * 10**5, 6 * 10**5))
    out = tmp_path / "runs"
    with pytest.raises(InputError, match=r"runs: only 0\.6 MB free on its disk; rosbag record refuses"):
        if verb == "sweep":
            sweep(APP, APP.with_name("space.yaml"), out)
        else:
            plan = tmp_path / "plan.json"
            plan.write_text('{"format": "perfros-bag/plan@1", "problem": 1, "method": "greedy", '
                            '"status": "feasible", "objective": 1.0, "computers": {"here": {"kind": "robot", '
                            '"capacity": 100, "cpu": 10}}, "links": [], "nodes": {"camera": {"computer": '
                            '"here", "value": 5, "cpu": 10, "performance": 1, "weight": 1}}}')
            deploy(plan, APP, APP.with_name("space.yaml"), out)
    started = [p.pid for p in psutil.process_iter(["cmdline"]) if str(out) in " ".join(p.info["cmdline"] or [])]
    assert started == []  # nothing was started (no roscore, roslaunch or recorder for this folder)
    assert not list(out.glob("*.bag")) and not (out / "manifest.yaml").exists()


def test_exclude_matches_whole_topic_names_as_rosbag_does(tmp_path: Path) -> None:
    """rosbag record -x takes a topic out when the regex matches the whole name
    (boost::regex_match): so does Space.recorded."""
    doc = _with(["exclude"], "/robot[0-9]+/people/image")
    space = load_space(_write(tmp_path, doc))
    assert not space.recorded("/robot1/people/image") and not space.recorded("/robot12/people/image")
    assert space.recorded("/robot1/people/image_raw") and space.recorded("/x/robot1/people/image")
    assert space.recorded("/robot1/people/found")
    assert load_space(_write(tmp_path, _with(["repeats"], 1))).recorded("/robot1/people/image")  # no exclude


@pytest.mark.ros
def test_node_command_is_what_roslaunch_would_run(tmp_path: Path) -> None:
    """`roslaunch --args` for a node in a group namespace with an <env> and a remap, and
    `--dump-params`: what a node started in another namespace gets (checked against the
    launch file's own text)."""
    import os

    from perfros_bag.sweep.launchfile import launch_nodes, launch_params, node_command

    (tmp_path / "inner.launch").write_text("""<launch>
  <arg name="rate" default="5" />
  <node name="camera" pkg="image_publisher" type="image_publisher" args="/no/such.png">
    <remap from="image_raw" to="raw" />
    <param name="publish_rate" value="$(arg rate)" />
    <env name="PERFROS_TEST_ENV" value="a b" />
  </node>
</launch>""")
    (tmp_path / "app.launch").write_text("""<launch>
  <arg name="rate" default="7" />
  <group ns="robot2"><include file="$(dirname)/inner.launch"><arg name="rate" value="$(arg rate)" /></include></group>
</launch>""")
    launch = read_launch(tmp_path / "app.launch")
    env = dict(os.environ, ROS_HOME=str(tmp_path / "ros"))
    assert launch_nodes(launch, {"rate": "9"}, env, 30) == ["/robot2/camera"]
    cmd = node_command(launch, "/robot2/camera", {"rate": "9"}, env, 30)
    assert cmd.node == "/robot2/camera"
    assert cmd.env == {"ROS_NAMESPACE": "/robot2", "PERFROS_TEST_ENV": "a b"}
    assert cmd.argv == ("/usr/lib/image_publisher/image_publisher", "/no/such.png", "image_raw:=raw", "__name:=camera")
    assert launch_params(launch, {"rate": "9"}, env, 30) == {"/robot2/camera/publish_rate": 9}
