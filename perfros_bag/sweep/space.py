"""``space.yaml``: what ``sweep`` varies in the user's launch file, and the runs that follow.

::

    duration_s: 20                 # recording length per run
    settle_s: 5                    # wait after every node publishes, before recording
    repeats: 1                     # runs per setting
    design: one-at-a-time          # | grid
    startup_timeout_s: 30          # optional: how long nodes and topics may take to come up
    exclude: '.*/debug_image$'     # optional: topics not recorded (a regex, rosbag record -x)
    vary:
      - node: detector             # ROS node name as launched (leading slash optional)
        parameter: {name: rate, unit: Hz}
        arg: detector_rate         # the roslaunch <arg> that sets it ...
        # param: /detector/rate    # ... or a ROS parameter set before the node starts
        values: [2, 5, 10]
        default: 5                 # optional: its value while another entry varies
    replay:                        # optional: recorded data stands in for nodes (perfros_bag.sweep.replay)
      recording: robot_day1.bag    # ROS 1 bag, rosbag2 directory or MCAP file (relative to space.yaml)
      replaces: [camera]           # launch-file nodes not started: the recording supplies their topics
      topics: [/camera/image_raw]  # optional; default: every recorded topic a replaced node published
      rates: [0.5, 1, 2]           # play-rate factors; every run of the design is played at each factor

With ``replay:``, ``vary:`` may be left out (the factors are then the only dimension).

Every problem is one :class:`~perfros_bag.errors.InputError` naming the file and the field.
"""

from __future__ import annotations

import enum
import hashlib
import itertools
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from perfros_bag.doccheck import Doc
from perfros_bag.errors import InputError
from perfros_bag.fileio import read_yaml, unknown_keys
from perfros_bag.system.names import NameKind, name_problem

Value = int | float | str

TOP_KEYS = {"duration_s", "settle_s", "repeats", "design", "startup_timeout_s", "exclude", "vary", "replay"}
VARY_KEYS = {"node", "parameter", "arg", "param", "values", "default"}
PARAMETER_KEYS = {"name", "unit"}
REPLAY_KEYS = {"recording", "replaces", "topics", "rates"}
#: The topic each replay player publishes once per loop, one mean message period after the last
#: replayed message, so that a loop restart keeps the recorded spacing (see
#: :mod:`perfros_bag.sweep.replay`). The tool's own: never recorded, never in graph.yaml.
LOOP_TOPIC = "/perfros_replay/loop"
#: Topics a replay player advertises of its own: its loop topic, and ``/clock`` (rosbag play
#: always advertises it; it publishes there only with ``--clock``, which the tool does not use).
PLAYER_TOPICS = frozenset({LOOP_TOPIC, "/clock"})


class Design(enum.Enum):
    ONE_AT_A_TIME = "one-at-a-time"
    GRID = "grid"


@dataclass(frozen=True)
class Parameter:
    name: str
    unit: str | None


@dataclass(frozen=True)
class Varied:
    """One thing to vary: a node's parameter, reached through a launch ``<arg>`` or a ROS
    parameter."""

    node: str  # the ROS node name, with its leading slash
    parameter: Parameter
    arg: str | None
    param: str | None
    values: tuple[Value, ...]
    default: Value | None = None

    @property
    def system_name(self) -> str:
        """The node's name in manifest.yaml and system.yaml (see :func:`system_node_name`)."""
        from perfros_bag.system.names import system_node_name

        return system_node_name(self.node)


@dataclass(frozen=True)
class Replay:
    """``replay:``: a recording plays the topics of the nodes it replaces, at each factor."""

    recording: Path  # resolved against space.yaml's folder
    replaces: tuple[str, ...]  # ROS node names, with their leading slash
    topics: tuple[str, ...] | None  # None: every recorded topic a replaced node published
    rates: tuple[float, ...]  # play-rate factors, each > 0

    @property
    def system_names(self) -> tuple[str, ...]:
        """The replaced nodes as manifest.yaml and system.yaml name them."""
        from perfros_bag.system.names import system_node_name

        return tuple(system_node_name(n) for n in self.replaces)


#: A replaced node's parameter in the manifest and the draft: its topics' replayed rate.
REPLAYED_PARAMETER = Parameter("rate", "Hz")


@dataclass(frozen=True)
class Space:
    path: Path
    duration_s: float
    settle_s: float
    repeats: int
    design: Design
    vary: tuple[Varied, ...]
    startup_timeout_s: float = 30.0
    exclude: str | None = None  # topics not recorded: a regex the whole name matches (rosbag record -x)
    replay: Replay | None = None

    def recorded(self, topic: str) -> bool:
        """Whether runs record ``topic`` (``exclude`` does not match it; a replay's loop
        topic is the tool's own)."""
        if self.replay is not None and topic == LOOP_TOPIC:
            return False
        return self.exclude is None or re.fullmatch(self.exclude, topic) is None

    @property
    def record_exclude(self) -> str | None:
        """The regex ``rosbag record -x`` is given: ``exclude``, and a replay's loop topic."""
        if self.replay is None:
            return self.exclude
        loop = re.escape(LOOP_TOPIC)
        return loop if self.exclude is None else f"(?:{self.exclude})|{loop}"

    def parameters(self) -> dict[str, Parameter]:
        """Every node the runs set, as system.yaml names it -> its parameter (a replaced
        node's is its replayed ``rate`` in Hz)."""
        out = {v.system_name: v.parameter for v in self.vary}
        if self.replay is not None:
            out.update(dict.fromkeys(self.replay.system_names, REPLAYED_PARAMETER))
        return out

    def with_duration(self, duration: float | None) -> Space:
        """This space with its recording length overridden (``None``: as it is)."""
        if duration is None:
            return self
        if not math.isfinite(duration) or duration <= 0:
            raise InputError(None, f"the recording duration must be a finite number > 0 s, got {duration:g}")
        return replace(self, duration_s=duration)


@dataclass(frozen=True)
class Run:
    """One run of the sweep: its name (the recording's stem) and what it sets."""

    name: str
    values: Mapping[str, Value]  # system node name -> value (every varied node)
    args: Mapping[str, str]  # roslaunch arg -> value
    params: Mapping[str, Value]  # ROS parameter -> value
    repeat: int
    factor: float | None = None  # replay: the recording's play-rate factor in this run
    #: nodelets run standalone (``nodelet standalone``) instead of in their manager (full ROS
    #: names); their managers are not started (perfros_bag.sweep.nodelets) unless ``keep_managers``
    standalone: tuple[str, ...] = ()
    #: with ``standalone``: the managers start all the same, and the nodelets not in
    #: ``standalone`` load into them (deploy: a plan's ``standalone: true`` nodes; the sweep's
    #: standalone run starts none)
    keep_managers: bool = False


def load_space(path: str | Path) -> Space:
    p = Path(path)
    return parse_space(read_yaml(p), p)


def parse_space(data: Any, path: Path) -> Space:
    doc = Doc(path)
    fail = doc.fail
    if data is None:
        raise fail("", "the file is empty (expected 'vary:')")
    doc.mapping(data, "", TOP_KEYS, expected="a mapping with 'vary:'")
    duration = _number(data.get("duration_s", 20), "duration_s", fail, positive=True)
    settle = _number(data.get("settle_s", 5), "settle_s", fail, positive=False)
    timeout = _number(data.get("startup_timeout_s", 30), "startup_timeout_s", fail, positive=True)
    repeats = data.get("repeats", 1)
    if isinstance(repeats, bool) or not isinstance(repeats, int) or repeats < 1:
        raise fail("repeats", f"must be a whole number >= 1, got {repeats!r}")
    design = doc.enum(data.get("design", Design.ONE_AT_A_TIME.value), "design", Design,
                      wording="must be 'one-at-a-time' or 'grid'")
    replay = _replay(data["replay"], path, doc) if data.get("replay") is not None else None
    raw_vary = data.get("vary")
    if raw_vary is None and replay is None:
        raise fail("", "missing 'vary:' (a list of {node, parameter, arg or param, values})")
    if raw_vary is not None and (not isinstance(raw_vary, list) or not raw_vary):
        raise fail("vary", f"must be a non-empty list, got {raw_vary!r}")
    vary = tuple(_varied(item, f"vary[{i}]", doc) for i, item in enumerate(raw_vary or []))
    for v in vary:
        if replay is not None and v.node in replay.replaces:
            raise fail("vary", f"node {v.node} is replaced by the replay (not started): it cannot be varied")
    nodes = [v.node for v in vary]
    for node in nodes:
        if nodes.count(node) > 1:
            raise fail("vary", f"node {node} is listed twice (a node has one parameter)")
    for what in ("arg", "param"):
        reached = [getattr(v, what) for v in vary if getattr(v, what) is not None]
        for r in reached:
            if reached.count(r) > 1:
                raise fail("vary", f"{what} {r!r} is set by two entries")
    exclude = data.get("exclude")
    if exclude is not None:
        if not isinstance(exclude, str) or not exclude:
            raise fail("exclude", f"must be a regular expression (a string), got {exclude!r}")
        try:
            re.compile(exclude)
        except re.error as exc:
            raise fail("exclude", f"not a regular expression: {exc}") from None
    return Space(path, duration, settle, repeats, design, vary, timeout, exclude, replay)


def _replay(raw: Any, path: Path, doc: Doc) -> Replay:
    fail = doc.fail
    doc.mapping(raw, "replay", REPLAY_KEYS, expected="a mapping {recording, replaces, topics, rates}")
    recording = raw.get("recording")
    if not isinstance(recording, str) or not recording.strip():
        raise fail("replay.recording", f"must be the path of a recording, got {recording!r}")
    replaces = raw.get("replaces")
    if not isinstance(replaces, list) or not replaces:
        raise fail("replay.replaces", f"must be a non-empty list of node names, got {replaces!r}")
    nodes = []
    for node in replaces:
        problem = name_problem(NameKind.GRAPH_NODE, node)
        if problem is not None or not isinstance(node, str):
            raise fail("replay.replaces", f"{node!r} {problem}")
        nodes.append("/" + node.lstrip("/"))
    if len(set(nodes)) < len(nodes):
        raise fail("replay.replaces", f"lists a node twice: {replaces!r}")
    topics = raw.get("topics")
    if topics is not None:
        if not isinstance(topics, list) or not topics:
            raise fail("replay.topics", f"must be a non-empty list of topic names, got {topics!r}")
        for t in topics:
            problem = name_problem(NameKind.TOPIC, t)
            if problem is not None or not isinstance(t, str) or not t.startswith("/") or t == LOOP_TOPIC:
                raise fail("replay.topics", f"{t!r}: {problem or 'must be an absolute topic name (as recorded)'}")
        if len(set(topics)) < len(topics):
            raise fail("replay.topics", f"lists a topic twice: {topics!r}")
    rates = raw.get("rates", [1])
    if not isinstance(rates, list) or not rates:
        raise fail("replay.rates", f"must be a non-empty list of play-rate factors, got {rates!r}")
    for r in rates:
        if isinstance(r, bool) or not isinstance(r, int | float) or not math.isfinite(r) or r <= 0:
            raise fail("replay.rates", f"a factor must be a number > 0, got {r!r}")
    if len({float(r) for r in rates}) < len(rates):
        raise fail("replay.rates", f"lists a factor twice: {rates!r}")
    return Replay((path.parent / recording).absolute(), tuple(nodes), None if topics is None else tuple(topics),
                  tuple(float(r) for r in rates))


def _varied(item: Any, where: str, doc: Doc) -> Varied:
    fail = doc.fail
    doc.mapping(item, where, VARY_KEYS, expected="a mapping {node, parameter, arg, values}")
    node = item.get("node")
    problem = name_problem(NameKind.GRAPH_NODE, node)
    if problem is not None or not isinstance(node, str):
        raise fail(f"{where}.node", f"{node!r} {problem}")
    node = "/" + node.lstrip("/")
    where = f"{where} (node {node})"
    pm = item.get("parameter")
    if not isinstance(pm, Mapping) or not isinstance(pm.get("name"), str) or not pm["name"].strip():
        raise fail(f"{where}.parameter", f"must be {{name: NAME, unit: UNIT}}, got {pm!r}")
    pbad = unknown_keys(pm, PARAMETER_KEYS)
    if pbad:
        raise fail(f"{where}.parameter", pbad)
    unit = pm.get("unit")
    if unit is not None and not isinstance(unit, str | int | float):
        raise fail(f"{where}.parameter.unit", f"must be a string, got {unit!r}")
    parameter = Parameter(pm["name"].strip(), None if unit is None else str(unit))
    arg, param = item.get("arg"), item.get("param")
    if (arg is None) == (param is None):
        raise fail(where, "needs exactly one of 'arg' (a roslaunch <arg>) or 'param' (a ROS parameter)")
    if arg is not None and (not isinstance(arg, str) or not re.match(r"^[A-Za-z_][A-Za-z0-9_.\-]*$", arg)):
        raise fail(f"{where}.arg", f"must be a roslaunch arg name, got {arg!r}")
    if param is not None and (name_problem(NameKind.PARAMETER, param) is not None or param.endswith("/")):
        raise fail(f"{where}.param", f"must be a ROS parameter name, got {param!r}")
    if param is not None and not param.startswith("/"):
        param = f"{node}/{param}"  # a private parameter of the node
    values = item.get("values")
    if not isinstance(values, list) or not values:
        raise fail(f"{where}.values", f"must be a non-empty list, got {values!r}")
    kinds = set()
    for v in values:
        if isinstance(v, bool) or not isinstance(v, int | float | str):
            raise fail(f"{where}.values", f"must be numbers or strings, got {v!r}")
        if isinstance(v, float) and not math.isfinite(v):
            raise fail(f"{where}.values", f"must be finite, got {v!r}")
        kinds.add("string" if isinstance(v, str) else "number")
    if len(kinds) > 1:
        raise fail(f"{where}.values", f"mixes numbers and strings: {values!r}")
    if len({_key(v) for v in values}) < len(values):
        raise fail(f"{where}.values", f"lists a value twice: {values!r}")
    default = item.get("default")
    if default is not None and (isinstance(default, bool) or not isinstance(default, int | float | str)
                                or ("string" if isinstance(default, str) else "number") not in kinds):
        raise fail(f"{where}.default", f"must be of the same type as the values, got {default!r}")
    return Varied(node, parameter, arg, param, tuple(values), default)


def _number(raw: Any, where: str, fail: Any, *, positive: bool) -> float:
    if isinstance(raw, bool) or not isinstance(raw, int | float) or not math.isfinite(raw) \
            or raw < 0 or (positive and raw == 0):
        raise fail(where, f"must be a number {'> 0' if positive else '>= 0'} (seconds), got {raw!r}")
    return float(raw)



def _key(v: Value) -> str:
    return repr(float(v)) if isinstance(v, int | float) else repr(v)


def arg_text(v: Value) -> str:
    """A value as a roslaunch ``name:=value`` argument."""
    if isinstance(v, float) and v.is_integer():
        return repr(v)  # 5.0 stays a float for roslaunch's type guessing
    return str(v)


def plan_runs(space: Space, arg_defaults: Mapping[str, str | None]) -> list[Run]:
    """The runs of the design, each ``repeats`` times, in order.

    ``one-at-a-time``: each entry takes its values while the others stay at their default
    (``default:``, else the launch file's ``<arg>`` default, else the first value); a
    setting that repeats an earlier one (all at default) runs once. ``grid``: every
    combination. ``arg_defaults``: the launch file's declared args and their defaults."""
    defaults = {v.node: default_value(v, arg_defaults) for v in space.vary}
    settings: list[dict[str, Value]] = []
    if not space.vary:
        settings.append({})
    elif space.design is Design.GRID:
        for combo in itertools.product(*(v.values for v in space.vary)):
            settings.append({v.node: x for v, x in zip(space.vary, combo, strict=True)})
    else:
        seen: set[str] = set()
        for v in space.vary:
            for x in v.values:
                s = {**defaults, v.node: x}
                key = json.dumps({k: _key(val) for k, val in s.items()}, sort_keys=True)
                if key not in seen:
                    seen.add(key)
                    settings.append(s)
    runs: list[Run] = []
    names: set[str] = set()
    factors: tuple[float | None, ...] = (None,) if space.replay is None else space.replay.rates
    for s in settings:
        for factor in factors:
            stem = "__".join(x for x in (_stem(space, s), _factor_part(factor)) if x)
            for rep in range(space.repeats):
                name = stem if space.repeats == 1 else f"{stem}_r{rep + 1}"
                if name in names:  # two values that read the same once made file-safe
                    key = json.dumps([s, factor], sort_keys=True, default=str)
                    name += "_" + hashlib.sha1(key.encode()).hexdigest()[:6]
                names.add(name)
                runs.append(Run(
                    name,
                    {v.system_name: s[v.node] for v in space.vary},
                    {v.arg: arg_text(s[v.node]) for v in space.vary if v.arg is not None},
                    {v.param: s[v.node] for v in space.vary if v.param is not None},
                    rep + 1,
                    factor,
                ))
    return runs


def _factor_part(factor: float | None) -> str:
    """A replay run's part of its name: ``replay-x0.5``."""
    return "" if factor is None else re.sub(r"[^A-Za-z0-9._=-]+", "_", f"replay-x{factor:g}")


def default_value(v: Varied, arg_defaults: Mapping[str, str | None]) -> Value:
    """An entry's value while another varies: ``default``, else the launch file's ``<arg>``
    default, else its first value."""
    if v.default is not None:
        return v.default
    if v.arg is not None and arg_defaults.get(v.arg) is not None:
        text = str(arg_defaults[v.arg])
        if all(isinstance(x, str) for x in v.values):
            return text
        try:
            number = float(text)
        except ValueError:
            return v.values[0]
        return int(number) if number.is_integer() and all(isinstance(x, int) for x in v.values) else number
    return v.values[0]


def _stem(space: Space, s: Mapping[str, Value]) -> str:
    parts = []
    for v in space.vary:
        x = s[v.node]
        text = arg_text(x) if not isinstance(x, float) else f"{x:g}"
        parts.append(f"{v.system_name}-{v.parameter.name}-{text}")
    return re.sub(r"[^A-Za-z0-9._=-]+", "_", "__".join(parts))
