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
    return _run_roslaunch([ROSLAUNCH, *what, *launch_argv(launch, args)], launch, f"roslaunch {what[0]}",
                          env, timeout)


def _run_roslaunch(argv: list[str], launch: LaunchFile, what: str, env: Mapping[str, str], timeout: float,
                   stdin: str | None = None) -> str:
    """Run one of roslaunch's tools on the launch file; its error as one :class:`InputError`."""
    try:
        done = subprocess.run(argv, capture_output=True, text=True, env=dict(env), timeout=timeout, check=False,
                              input=stdin)
    except FileNotFoundError:
        raise InputError(None, f"{ROSLAUNCH} not found: install Debian's ROS 1 (apt-get install ros-core)") from None
    except subprocess.TimeoutExpired:
        raise InputError(launch.path, f"{what} took more than {timeout:g} s") from None
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


@dataclass(frozen=True)
class ResolvedNode:
    """One ``<node>`` as roslaunch's own loader resolves it (args, includes, groups, ``<env>``
    and ``<remap>`` applied)."""

    package: str
    type: str
    name: str
    namespace: str  # "/" or "/ns/" as roslaunch keeps it
    args: str
    remaps: tuple[tuple[str, str], ...]
    env: tuple[tuple[str, str], ...]
    machine: str | None  # the launch file's own machine= (None: none)
    file: str  # the launch file that declares it
    options: Mapping[str, str]  # respawn, respawn_delay, required, output, cwd, launch-prefix, clear_params when set

    @property
    def full_name(self) -> str:
        return self.namespace.rstrip("/") + "/" + self.name


@dataclass(frozen=True)
class Resolved:
    """A launch file with a set of args, as roslaunch resolves it."""

    nodes: tuple[ResolvedNode, ...]
    params: Mapping[str, object]  # every ROS parameter it sets, by full name
    machines: Mapping[str, Mapping[str, str]]  # its own <machine>s: name -> launch attributes
    error: str | None = None  # roslaunch could not load it with these args


# Run by the interpreter of Debian's roslaunch (the one on its #! line): its own XML loader,
# as `roslaunch --nodes/--args/--dump-params` use it, without starting anything.
_RESOLVE = r"""
import json, sys
import roslaunch.config, roslaunch.core, roslaunch.xmlloader
req = json.load(sys.stdin)
out = []
for argv in req["argsets"]:
    try:
        cfg = roslaunch.config.ROSLaunchConfig()
        loader = roslaunch.xmlloader.XmlLoader()
        loader.ignore_unset_args = False  # as roslaunch itself: a required arg left unset is an error
        loader.load(req["path"], cfg, argv=["roslaunch"] + argv, verbose=False)
        params = {}
        for k, p in cfg.params.items():
            v = p.value
            if not isinstance(v, (bool, int, float, str, list, dict)) or isinstance(v, bytes):
                raise ValueError("parameter %s: a %s value cannot be written back" % (k, type(v).__name__))
            params[k] = v
        nodes = []
        for n in cfg.nodes:
            opts = {"respawn": "true" if n.respawn else None,
                    "respawn_delay": repr(n.respawn_delay) if n.respawn_delay else None,
                    "required": "true" if n.required else None, "output": n.output, "cwd": n.cwd,
                    "launch-prefix": n.launch_prefix,
                    "clear_params": "true" if (n.namespace + n.name + "/") in cfg.clear_params else None}
            nodes.append({"package": n.package, "type": n.type, "name": n.name, "namespace": n.namespace,
                          "args": n.args or "", "remaps": [list(r) for r in n.remap_args],
                          "env": [list(e) for e in n.env_args], "machine": n.machine_name or None,
                          "file": n.filename or "", "options": {k: str(v) for k, v in opts.items() if v}})
        machines = {}
        for name, m in cfg.machines.items():
            if not name:
                continue
            # only what the file gave: roslaunch's defaults are left to roslaunch where it runs
            default_loader = roslaunch.config.calculate_env_loader()
            attrs = {"address": m.address, "user": m.user, "password": m.password,
                     "env-loader": m.env_loader if m.env_loader != default_loader else None,
                     "ssh-port": str(m.ssh_port) if m.ssh_port and int(m.ssh_port) != 22 else None,
                     "timeout": repr(m.timeout) if m.timeout != roslaunch.core._DEFAULT_REGISTER_TIMEOUT else None}
            machines[name] = {k: str(v) for k, v in attrs.items() if v}
        out.append({"nodes": nodes, "params": params, "machines": machines})
    except Exception as exc:
        out.append({"error": "%s: %s" % (type(exc).__name__, exc) if not str(exc) else str(exc)})
json.dump(out, sys.stdout)
"""


def roslaunch_python() -> str:
    """The interpreter Debian's ``roslaunch`` runs under (its ``#!`` line): the one whose
    ``roslaunch`` package is that roslaunch."""
    import shlex
    import shutil

    found = shutil.which(ROSLAUNCH)
    if found is None:
        raise InputError(None, f"{ROSLAUNCH} not found: install Debian's ROS 1 (apt-get install ros-core)")
    with open(found, "rb") as f:
        first = f.readline().decode("utf-8", "replace")
    words = shlex.split(first[2:]) if first.startswith("#!") else []
    if words and words[0].endswith("/env"):
        words = words[1:]
    if not words:
        raise InputError(None, f"{found}: no #! line naming its Python interpreter")
    return words[0]


def resolve_launch(launch: LaunchFile, argsets: list[Mapping[str, str]], env: Mapping[str, str],
                   timeout: float) -> list[Resolved]:
    """The launch file resolved by roslaunch's own loader once per set of args (one process).
    A set roslaunch cannot load gives a :class:`Resolved` with its ``error``."""
    import json

    request = json.dumps({"path": str(launch.path.absolute()),
                          "argsets": [[f"{k}:={v}" for k, v in args.items()] for args in argsets]})
    env = {k: v for k, v in env.items() if k != "PYTHONPATH"}  # Debian's Python, not ours
    text = _run_roslaunch([roslaunch_python(), "-c", _RESOLVE], launch, "roslaunch's loader", env, timeout,
                          stdin=request)
    try:
        answers = json.loads(text)
    except ValueError:
        raise InputError(launch.path, "roslaunch's loader gave no answer") from None
    out = []
    for a in answers:
        if "error" in a:
            out.append(Resolved((), {}, {}, " ".join(x.strip() for x in a["error"].splitlines() if x.strip())
                                or "error"))
            continue
        nodes = tuple(ResolvedNode(n["package"], n["type"], n["name"], n["namespace"], n["args"],
                                   tuple((r[0], r[1]) for r in n["remaps"]), tuple((e[0], e[1]) for e in n["env"]),
                                   n["machine"], n["file"], n["options"]) for n in a["nodes"])
        out.append(Resolved(nodes, a["params"], a["machines"]))
    return out
