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
from dataclasses import replace
from pathlib import Path
from typing import Any

import yaml

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.export.writers import add_machines, check_plan_names, rounded_value
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


def _uses(real: Resolved, marked: Resolved, markers: Mapping[str, str]) -> dict[str, Any] | None:
    """Where each marker landed: ``{"params": {name: arg}, "text": {marker: arg}}``; None when
    the markers changed what the file starts (an arg in a condition or an expression)."""
    if [n.full_name for n in real.nodes] != [n.full_name for n in marked.nodes] or set(real.params) != set(marked.params):
        return None
    params = {}
    for name, value in marked.params.items():
        for arg, mark in markers.items():
            if _is_mark(value, mark):
                params[name] = arg
    return {"params": params, "text": {mark: arg for arg, mark in markers.items()}}


def _is_mark(value: object, mark: str) -> bool:
    """Whether a resolved parameter holds the marker (as roslaunch typed it: text or number)."""
    if isinstance(value, str):
        return value == mark
    if isinstance(value, bool) or not isinstance(value, int | float) or mark.startswith("perfros_marker_"):
        return False
    return float(value) == float(mark)


def _with_args(text: str, original: str, text_marks: Mapping[str, str]) -> str:
    """``text`` (resolved with markers) with each marker as ``$(arg NAME)``; the plan's own
    resolution ``original`` when no marker is in it."""
    out = text
    for mark, arg in text_marks.items():
        out = out.replace(mark, f"$(arg {arg})")
    return out if out != text else original


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


def _param(parent: ET.Element, name: str, value: object, arg: str | None) -> None:
    if isinstance(value, list | dict):
        el = ET.SubElement(parent, "rosparam", {"param": name})
        el.text = yaml.safe_dump(value, default_flow_style=True).strip()
        return
    ET.SubElement(parent, "param", {"name": name, "type": _type(value),
                                    "value": f"$(arg {arg})" if arg is not None else _text(value)})


def _node(root: ET.Element, real: ResolvedNode, marked: ResolvedNode | None, machine: str | None,
          params: Mapping[str, object], param_args: Mapping[str, str], text_marks: Mapping[str, str]) -> None:
    attrs = {"name": real.name, "pkg": real.package, "type": real.type}
    if real.namespace.strip("/"):
        attrs["ns"] = real.namespace.rstrip("/")
    if machine is not None:
        attrs["machine"] = machine
    if real.args:
        attrs["args"] = _with_args(marked.args, real.args, text_marks) if marked else real.args
    attrs.update(real.options)
    el = ET.SubElement(root, "node", attrs)
    el.append(ET.Comment(f" from {real.file} "))
    for i, (a, b) in enumerate(real.remaps):
        ma, mb = marked.remaps[i] if marked and i < len(marked.remaps) else (a, b)
        ET.SubElement(el, "remap", {"from": _with_args(ma, a, text_marks), "to": _with_args(mb, b, text_marks)})
    for i, (k, v) in enumerate(real.env):
        mv = marked.env[i][1] if marked and i < len(marked.env) else v
        ET.SubElement(el, "env", {"name": k, "value": _with_args(mv, v, text_marks)})
    prefix = real.full_name + "/"
    for name, value in params.items():
        if name.startswith(prefix):
            _param(el, name[len(prefix):], value, param_args.get(name))


def planned_launch_xml(plan: Plan, system: System | None, launch: LaunchFile, space: Space, *,
                       plan_path: str | None = None, env: Mapping[str, str] | None = None) -> str:
    """The user's launch file with the plan applied (see the module's doc)."""
    from perfros_bag.sweep.deploy import plan_run

    plan.require_feasible(plan_path, "export")
    check_plan_names(plan, plan_path)
    check_space(launch, space)
    check_space_against_plan(plan, space)
    run = plan_run(_rounded(plan, system), space, dict(launch.args))
    markers = {arg: _marker(text, i) for i, (arg, text) in enumerate(run.args.items())}
    real, marked = resolve_launch(launch, [run.args, markers], os.environ if env is None else env, RESOLVE_TIMEOUT_S)
    if real.error is not None:
        raise InputError(launch.path, f"roslaunch cannot read it: {real.error}")
    by_name = {system_node_name(n.full_name): n for n in real.nodes}
    missing = [n for n in plan.nodes if n not in by_name]
    if missing:
        started = ", ".join(n.full_name for n in real.nodes) or "none"
        raise InputError(launch.path, f"the plan's node(s) {', '.join(missing)} are not in it (it starts: {started}); "
                         "not the launch file the plan was made from")
    uses = _uses(real, marked, markers) if marked.error is None and markers else None
    param_args: dict[str, str] = uses["params"] if uses else {}
    text_marks: dict[str, str] = uses["text"] if uses else {}
    params: dict[str, object] = dict(real.params)
    kept: list[str] = []
    for v in space.vary:
        if v.param is not None and v.system_name in plan.nodes:
            if v.param in params:  # the launch file sets it itself: as in the sweep, its value wins
                kept.append(v.param)
            else:
                params[v.param] = run.params[v.param]

    root = ET.Element("launch")
    root.append(ET.Comment(f" generated by perfros-bag from {launch.path.absolute()} and {plan_path or 'the plan'}: "
                           f"problem {plan.problem}, {len(plan.nodes)} planned nodes on {len(plan.computers)} "
                           "computers; the launch file as Debian's roslaunch resolves it, includes flattened "
                           "(each node names the file that declares it) "))
    add_machines(root, plan, system)
    for user_machine, attrs in real.machines.items():  # the user's own, for the nodes the plan leaves alone
        if user_machine not in plan.computers and any(n.machine == user_machine for n in real.nodes):
            ET.SubElement(root, "machine", {"name": user_machine, **attrs})
    for arg, text in run.args.items():
        used = uses is not None and (arg in param_args.values() or any(
            a == arg and _appears(mark, marked) for mark, a in text_marks.items()))
        doc = "the plan's value, through space.yaml's arg" + ("" if used else
                                                               " (where roslaunch uses it could not be traced: "
                                                               "the nodes below hold its value)")
        ET.SubElement(root, "arg", {"name": arg, "default": text, "doc": doc})
    if kept:
        root.append(ET.Comment(" set by the launch file itself, which wins over space.yaml's param as in the "
                               f"sweep: {', '.join(kept)} "))
    node_names = {n.full_name for n in real.nodes}
    for name, value in params.items():  # parameters no node owns
        if not any(name.startswith(n + "/") for n in node_names):
            _param(root, name, value, param_args.get(name))
    marked_nodes = {n.full_name: n for n in marked.nodes} if uses else {}
    unknown = [n for n in real.nodes if system_node_name(n.full_name) not in plan.nodes]
    for n in real.nodes:
        planned = plan.nodes.get(system_node_name(n.full_name))
        _node(root, n, marked_nodes.get(n.full_name), planned.computer if planned else n.machine, params,
              param_args, text_marks)
    if unknown:
        root.append(ET.Comment(" nodes the plan does not know, at their launch defaults (and machine): "
                               + ", ".join(n.full_name for n in unknown) + " "))
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _appears(mark: str, marked: Resolved) -> bool:
    for n in marked.nodes:
        if mark in n.args or any(mark in a or mark in b for a, b in n.remaps) or any(mark in v for _, v in n.env):
            return True
    return False


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
