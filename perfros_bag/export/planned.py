"""The plan as the user's own launch file (``export --format roslaunch --launch APP.launch
--space space.yaml``).

roslaunch cannot place a node it includes from another file on a machine (``<include>`` has
no ``machine=``; a ``<machine default="true">`` around an include puts every node of it on
that one machine), so a wrapper that includes the user's file cannot give two nodes of one
file two computers. The file is therefore written from what Debian's roslaunch itself
resolves (:func:`perfros_bag.sweep.launchfile.resolve_launch`: its XML loader, the one
``roslaunch --nodes/--args/--dump-params`` use) with the plan's values set through
space.yaml's channels: every node with its package, type, name, namespace, args, remaps,
``<env>``, options and parameters, and ``machine=`` its plan computer; the includes are
flattened (each node says which file declared it).

A varied node's value keeps its channel: an ``arg`` of space.yaml is declared in the written
file with the plan value as its default, and used wherever the user's file used it (found by
resolving once more with a marker value per arg: a parameter, args, remap or ``<env>`` value
that carries the marker is written as ``$(arg NAME)``), so ``roslaunch planned.launch
camera_rate:=12`` still works; a ``param`` is written as that ROS parameter. Everything is
built with :mod:`xml.etree.ElementTree`, which escapes every attribute and text.
"""

from __future__ import annotations

import os
import warnings
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from pathlib import Path

import yaml

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.export.writers import add_machines, check_plan_names, comment, rounded_value
from perfros_bag.sweep.launchfile import (
    LaunchFile,
    Resolved,
    ResolvedNode,
    check_space,
    read_launch,
    resolve_launch,
)
from perfros_bag.sweep.space import Space, load_space
from perfros_bag.system.names import system_node_name
from perfros_bag.system.plan import Plan
from perfros_bag.system.types import System

RESOLVE_TIMEOUT_S = 60.0
_MARK = 918273645  # a number no launch file holds: where an arg's marker lands, the arg was used


def check_space_against_plan(plan: Plan, space: Space) -> None:
    """space.yaml must reach every planned value, by the parameter the plan names."""
    varied = {v.system_name: v for v in space.vary}
    for name, pn in plan.nodes.items():
        v = varied.get(name)
        if v is not None and pn.parameter is not None and v.parameter.name != pn.parameter:
            raise InputError(space.path, f"node {v.node}: varies parameter {v.parameter.name!r}, the plan sets "
                             f"{pn.parameter!r}: not the space.yaml the plan was made from")
        if v is None and pn.parameter is not None and pn.value is not None:
            raise InputError(space.path, f"the plan sets node {name}'s {pn.parameter!r} to {pn.value:g}, but "
                             "space.yaml says no arg or param that reaches it")
    unknown = sorted(v.system_name for v in space.vary if v.system_name not in plan.nodes)
    if unknown:
        warnings.warn(f"{space.path}: node(s) {', '.join(unknown)} not in the plan: kept at their launch default",
                      PerfrosWarning, stacklevel=3)


def _rounded(plan: Plan, system: System | None) -> Plan:
    """The plan with every value as export writes it (9 significant digits, int where typed)."""
    nodes = {n: replace(pn, value=rounded_value(plan, system, n)) for n, pn in plan.nodes.items()}
    return replace(plan, nodes=nodes)


def _marker(text: str, i: int) -> str:
    """A value for arg ``i`` that roslaunch types as it types ``text``, and that no launch file holds."""
    try:
        int(text)
        return str(_MARK + i)
    except ValueError:
        pass
    try:
        float(text)
        return f"{_MARK + i}.5"
    except ValueError:
        return f"perfros_marker_{i}_{_MARK}"


@dataclass
class _Marks:
    """Where each arg's marker landed in the marked resolution (see the module's doc)."""

    marked: Resolved | None  # None: the markers changed what the file starts (an arg in a condition, an $(eval))
    text_args: dict[str, str] = field(default_factory=dict)  # marker -> arg

    @classmethod
    def find(cls, real: Resolved, marked: Resolved, markers: Mapping[str, str]) -> _Marks:
        same = marked.error is None and [n.full_name for n in real.nodes] == [n.full_name for n in marked.nodes] \
            and set(real.params) == set(marked.params)
        return cls(marked if same and markers else None, {mark: arg for arg, mark in markers.items()})

    def node(self, full_name: str) -> ResolvedNode | None:
        return next((n for n in self.marked.nodes if n.full_name == full_name), None) if self.marked else None

    def text(self, marked: str | None, real: str) -> str:
        """``marked`` with each marker as ``$(arg NAME)``; ``real`` when it holds none."""
        if marked is None:
            return real
        out = marked
        for mark, arg in self.text_args.items():
            out = out.replace(mark, f"$(arg {arg})")
        return out if out != marked else real

    def param(self, name: str, value: object) -> str:
        """A parameter's value as written: ``$(arg NAME)`` when it is an arg's whole value."""
        marked = self.marked.params.get(name) if self.marked else None
        for mark, arg in self.text_args.items():
            if _is_mark(marked, mark):
                return f"$(arg {arg})"
        return self.text(marked, value) if isinstance(value, str) and isinstance(marked, str) else _text(value)

    def used(self, arg: str) -> bool:
        if self.marked is None:
            return False
        mark = next(m for m, a in self.text_args.items() if a == arg)
        texts = [t for n in self.marked.nodes for t in (n.args, *(x for r in n.remaps for x in r),
                                                        *(v for _, v in n.env))]
        texts += [v for v in self.marked.params.values() if isinstance(v, str)]
        return any(mark in t for t in texts) or any(_is_mark(v, mark) for v in self.marked.params.values())


def _is_mark(value: object, mark: str) -> bool:
    """Whether a resolved parameter holds the marker (as roslaunch typed it: text or number)."""
    if isinstance(value, str):
        return value == mark
    if isinstance(value, bool) or not isinstance(value, int | float) or mark.startswith("perfros_marker_"):
        return False
    return float(value) == float(mark)


def _type(value: object) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "int"
    if isinstance(value, float):
        return "double"
    return "str"


def _text(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _param(parent: ET.Element, name: str, value: object, marks: _Marks, full_name: str) -> None:
    # <rosparam> (YAML) for what <param value=> cannot hold: lists, mappings, and text with
    # spaces at its ends (roslaunch strips a value= before typing it)
    if isinstance(value, list | dict) or isinstance(value, str) and value != value.strip():
        el = ET.SubElement(parent, "rosparam", {"param": name})
        el.text = yaml.safe_dump(value, default_flow_style=True).strip()
        return
    ET.SubElement(parent, "param", {"name": name, "type": _type(value), "value": marks.param(full_name, value)})


def _owner(param: str, nodes: list[str]) -> str | None:
    """The node whose private parameter ``param`` is (the deepest one), or None."""
    owners = [n for n in nodes if param.startswith(n + "/")]
    return max(owners, key=len) if owners else None


def _standalone_args(args: str) -> str:
    """A loader's ``args`` (``load PKG/TYPE MANAGER ...``) as ``standalone PKG/TYPE ...``
    (:func:`~perfros_bag.sweep.nodelets.standalone_argv`), split and joined as roslaunch
    splits them (shell words)."""
    import shlex

    from perfros_bag.sweep.nodelets import standalone_argv

    return shlex.join(standalone_argv(shlex.split(args)))


def _node(root: ET.Element, real: ResolvedNode, machine: str | None, params: Mapping[str, object],
          marks: _Marks, *, standalone: bool = False) -> None:
    """``real`` as a ``<node>`` on ``machine``; ``standalone``: a nodelet loader written as
    ``nodelet standalone`` (its name, remaps, ``<env>`` and parameters as they are)."""
    marked = marks.node(real.full_name)
    if standalone:
        real = replace(real, args=_standalone_args(real.args))
        if marked is not None:
            marked = replace(marked, args=_standalone_args(marked.args))
    attrs = {"name": real.name, "pkg": real.package, "type": real.type}
    if real.namespace.strip("/"):
        attrs["ns"] = real.namespace.rstrip("/")
    if machine is not None:
        attrs["machine"] = machine
    if real.args:
        attrs["args"] = marks.text(marked.args if marked else None, real.args)
    attrs.update(real.options)
    el = ET.SubElement(root, "node", attrs)
    el.append(comment(f"from {real.file}"))
    for i, (a, b) in enumerate(real.remaps):
        ma, mb = marked.remaps[i] if marked and i < len(marked.remaps) else (None, None)
        ET.SubElement(el, "remap", {"from": marks.text(ma, a), "to": marks.text(mb, b)})
    for i, (k, v) in enumerate(real.env):
        mv = marked.env[i][1] if marked and i < len(marked.env) else None
        ET.SubElement(el, "env", {"name": k, "value": marks.text(mv, v)})
    for name, value in params.items():
        _param(el, name[len(real.full_name) + 1:], value, marks, name)


def planned_launch_xml(plan: Plan, system: System | None, launch: LaunchFile, space: Space, *,
                       plan_path: str | None = None, env: Mapping[str, str] | None = None) -> str:
    """The user's launch file with the plan applied (see the module's doc)."""
    from perfros_bag.sweep.deploy import plan_run
    from perfros_bag.sweep.nodelets import check_nodelets, check_plan_membership, standalone_nodelets

    plan.require_feasible(plan_path, "export")
    check_plan_names(plan, plan_path)
    check_space(launch, space)
    run = plan_run(_rounded(plan, system), space, dict(launch.args))
    markers = {arg: _marker(text, i) for i, (arg, text) in enumerate(run.args.items())}
    real, marked = resolve_launch(launch, [run.args, markers], os.environ if env is None else env, RESOLVE_TIMEOUT_S)
    if real.error is not None:
        raise InputError(launch.path, f"roslaunch cannot read it: {real.error}")
    # its nodelets: each into a manager it starts, of a class its package exports, on its
    # manager's plan computer (the launch file fixes the membership) unless the plan runs it
    # standalone (membership: choose): then written as `nodelet standalone PKG/TYPE`
    alone = plan.standalone
    nodelets = check_nodelets(real, launch.path, elsewhere=True)
    check_plan_membership(nodelets, {n: pn.computer for n, pn in plan.nodes.items()}, plan_path, alone)
    standalone = set(standalone_nodelets(nodelets, alone, launch.path))
    by_name: dict[str, ResolvedNode] = {}
    for n in real.nodes:
        name = system_node_name(n.full_name)
        other = by_name.setdefault(name, n)
        if other is not n and name in plan.nodes:  # both would get the plan's machine and value
            raise InputError(launch.path, f"ROS nodes {other.full_name} and {n.full_name} both are the plan's node "
                             f"{name} (system.yaml joins namespaces with '_'): rename one of them")
    missing = [n for n in plan.nodes if n not in by_name]
    if missing:
        started = ", ".join(n.full_name for n in real.nodes) or "none"
        raise InputError(launch.path, f"the plan's node(s) {', '.join(missing)} are not in it (it starts: {started}); "
                         "not the launch file the plan was made from")
    check_space_against_plan(plan, space)
    marks = _Marks.find(real, marked, markers)
    params: dict[str, object] = dict(real.params)
    kept: list[str] = []
    for v in space.vary:
        if v.param is not None and v.system_name in plan.nodes:
            if v.param in params:  # the launch file sets it itself: as in the sweep, its value wins
                kept.append(v.param)
            else:
                params[v.param] = run.params[v.param]

    root = ET.Element("launch")
    root.append(comment(f"generated by perfros-bag from {launch.path.absolute()} and {plan_path or 'the plan'}: "
                        f"problem {plan.problem}, {len(plan.nodes)} planned nodes on {len(plan.computers)} "
                        "computers; the launch file as Debian's roslaunch resolves it, includes flattened "
                        "(each node names the file that declares it)"))
    add_machines(root, plan, system)
    for user_machine, attrs in real.machines.items():  # the user's own, for the nodes the plan leaves alone
        if user_machine not in plan.computers and any(n.machine == user_machine for n in real.nodes):
            ET.SubElement(root, "machine", {"name": user_machine, **attrs})
    for arg, text in run.args.items():
        doc = "the plan's value, through space.yaml's arg" + ("" if marks.used(arg) else
                                                               " (where roslaunch uses it could not be traced: "
                                                               "the nodes below hold its value)")
        ET.SubElement(root, "arg", {"name": arg, "default": text, "doc": doc})
    if kept:
        root.append(comment("set by the launch file itself, which wins over space.yaml's param as in the "
                            f"sweep: {', '.join(kept)}"))
    node_names = [n.full_name for n in real.nodes]
    owned: dict[str | None, dict[str, object]] = {}
    for name, value in params.items():
        owned.setdefault(_owner(name, node_names), {})[name] = value
    for name, value in owned.get(None, {}).items():  # parameters no node owns
        _param(root, name, value, marks, name)
    unknown = [n for n in real.nodes if system_node_name(n.full_name) not in plan.nodes]
    for n in real.nodes:
        planned = plan.nodes.get(system_node_name(n.full_name))
        _node(root, n, planned.computer if planned else n.machine, owned.get(n.full_name, {}), marks,
              standalone=n.full_name in standalone)
    if unknown:
        root.append(comment("nodes the plan does not know, at their launch defaults (and machine): "
                            + ", ".join(n.full_name for n in unknown)))
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def export_planned(plan_path: str | Path, launch_path: str | Path, space_path: str | Path, out: str | Path,
                   system_path: str | Path | None = None) -> str:
    """Read the plan, the launch file and space.yaml; write the planned launch file atomically."""
    from perfros_bag.fileio import atomic_write_text
    from perfros_bag.system.planfile import load_plan, plan_system

    plan = load_plan(plan_path)
    system = plan_system(plan, plan_path, system_path)
    text = planned_launch_xml(plan, system, read_launch(launch_path), load_space(space_path),
                              plan_path=str(plan_path))
    atomic_write_text(out, text)
    return text
