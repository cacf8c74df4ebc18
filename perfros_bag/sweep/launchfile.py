"""The user's launch file: read its ``<arg>`` declarations, ask roslaunch for its nodes."""

from __future__ import annotations

import subprocess
import xml.etree.ElementTree as ET
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path

from perfros_bag.errors import InputError
from perfros_bag.sweep.space import Space

ROSLAUNCH = "roslaunch"


@dataclass(frozen=True)
class LaunchFile:
    path: Path
    args: Mapping[str, str | None]  # settable <arg>s (no value=) -> default (None: required)
    fixed: frozenset[str]  # <arg>s with value=: roslaunch does not let a caller set them


def read_launch(path: str | Path) -> LaunchFile:
    """The launch file's top-level ``<arg>`` declarations (included files are not read:
    an arg is set on the command line of the file it is declared in)."""
    p = Path(path)
    if not p.is_file():
        raise InputError(p, "launch file not found" if not p.exists() else "is not a file, expected a launch file")
    try:
        root = ET.parse(p).getroot()  # noqa: S314 - the user's own launch file
    except ET.ParseError as exc:
        raise InputError(p, f"not a launch file: invalid XML ({exc})") from None
    except OSError as exc:
        raise InputError(p, f"cannot read the launch file: {exc.strerror or exc}") from None
    if root.tag != "launch":
        raise InputError(p, f"not a launch file: the root element is <{root.tag}>, expected <launch>")
    args: dict[str, str | None] = {}
    fixed: set[str] = set()
    for el in _declarations(root):
        name = el.get("name")
        if not name:
            continue
        if el.get("value") is not None:
            fixed.add(name)
        else:
            args.setdefault(name, el.get("default"))
    return LaunchFile(p, args, frozenset(fixed - set(args)))


def _declarations(el: ET.Element) -> Iterator[ET.Element]:
    """The ``<arg>`` elements of this file (an ``<include>``'s ``<arg>``s pass values on)."""
    for child in el:
        if child.tag == "include":
            continue
        if child.tag == "arg":
            yield child
        yield from _declarations(child)


def check_space(launch: LaunchFile, space: Space) -> None:
    """Every ``arg`` the space sets is declared in the launch file and settable."""
    for v in space.vary:
        if v.arg is None:
            continue
        if v.arg in launch.fixed:
            raise InputError(space.path, f"node {v.node}: arg {v.arg!r} has a fixed value= in {launch.path}: "
                             "roslaunch does not let a caller set it")
        if v.arg not in launch.args:
            declared = ", ".join(sorted(launch.args)) or "none"
            raise InputError(space.path, f"node {v.node}: arg {v.arg!r} is not declared in {launch.path} "
                             f"(its <arg>s: {declared})")


def launch_argv(launch: LaunchFile, args: Mapping[str, str]) -> list[str]:
    return [str(launch.path.absolute()), *(f"{k}:={v}" for k, v in args.items())]


def launch_nodes(launch: LaunchFile, args: Mapping[str, str], env: Mapping[str, str], timeout: float) -> list[str]:
    """The ROS names of the nodes the launch file starts with ``args`` (``roslaunch --nodes``)."""
    out = _roslaunch(launch, ["--nodes"], args, env, timeout)
    nodes = [x.strip() for x in out.splitlines() if x.strip().startswith("/")]
    if not nodes:
        raise InputError(launch.path, "the launch file starts no node")
    return nodes


@dataclass(frozen=True)
class NodeCommand:
    """How roslaunch would start one node: its environment additions and command line."""

    node: str
    env: Mapping[str, str]
    argv: tuple[str, ...]


def _roslaunch(launch: LaunchFile, what: list[str], args: Mapping[str, str], env: Mapping[str, str],
               timeout: float) -> str:
    argv = [ROSLAUNCH, *what, *launch_argv(launch, args)]
    try:
        done = subprocess.run(argv, capture_output=True, text=True, env=dict(env), timeout=timeout, check=False)
    except FileNotFoundError:
        raise InputError(None, f"{ROSLAUNCH} not found: install Debian's ROS 1 (apt-get install ros-core)") from None
    except subprocess.TimeoutExpired:
        raise InputError(launch.path, f"roslaunch {what[0]} took more than {timeout:g} s") from None
    if done.returncode != 0:
        lines = [x.strip() for x in (done.stderr + done.stdout).splitlines() if x.strip()]
        cause = next((x for x in reversed(lines) if "error" in x.lower()), lines[-1] if lines else "no output")
        raise InputError(launch.path, f"roslaunch cannot read it: {cause}")
    return done.stdout


def node_command(launch: LaunchFile, node: str, args: Mapping[str, str], env: Mapping[str, str],
                 timeout: float) -> NodeCommand:
    """``roslaunch --args NODE``: the command line and environment roslaunch itself would
    use to start ``node`` (remappings, ``__name``, its namespace and ``<env>`` included), so
    a node can be started elsewhere (another network namespace) exactly as roslaunch would.
    roslaunch's own ``ROS_MASTER_URI`` is left out: the caller gives the run's."""
    import shlex

    words = shlex.split(_roslaunch(launch, ["--args", node], args, env, timeout).strip())
    extra: dict[str, str] = {}
    while words and "=" in words[0] and not words[0].startswith(("/", "-")) \
            and words[0].split("=", 1)[0].isidentifier():
        key, value = words.pop(0).split("=", 1)
        extra[key] = value
    if not words:
        raise InputError(launch.path, f"roslaunch --args gave no command line for node {node}")
    extra.pop("ROS_MASTER_URI", None)
    return NodeCommand(node, extra, tuple(words))


def launch_params(launch: LaunchFile, args: Mapping[str, str], env: Mapping[str, str],
                  timeout: float) -> dict[str, object]:
    """``roslaunch --dump-params``: every ROS parameter the launch file sets, by full name."""
    import yaml

    data = yaml.safe_load(_roslaunch(launch, ["--dump-params"], args, env, timeout)) or {}
    if not isinstance(data, dict):
        raise InputError(launch.path, "roslaunch --dump-params did not give a mapping of parameters")
    return {str(k): v for k, v in data.items()}
