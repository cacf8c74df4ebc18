"""Deploy a plan: ROS 1 launch XML or a ROS 2 parameters YAML.

``roslaunch``: one ``<machine>`` per computer of the plan (attributes from the optional
``machines:`` map of system.yaml; otherwise ``address`` is a launch argument
``<computer>_address`` defaulting to the computer's name) and one ``<node>`` per plan node
with ``machine=`` and its parameter as ``<param>``. Package, type, parameter name, node
name and namespace come from the node's optional ``launch:`` fields; without them the
node's name is its type and the package is the placeholder ``PACKAGE``. The XML is built
with :mod:`xml.etree.ElementTree`, which escapes every attribute.

Every name written must be one ROS can run (:mod:`perfros_bag.system.names`): system.yaml's
are checked when it is read, and the plan's own (node, computer and parameter names) by
:func:`check_plan_names` before anything is written.

``ros2-params``: a ROS 2 parameters file (``<node>: {ros__parameters: {param: value}}``)
preceded by a placement table in comments (ROS 2 would read any extra top-level key as
a node), one line per node: ``# placement: <node> -> <computer>``, names JSON-quoted; and
beside it, per computer that runs a node, a ROS 2 XML launch file
``<stem>.<computer>.launch.xml`` naming its nodes and their parameter values.

With ``--launch`` and ``--space``, ``roslaunch`` is the user's own launch file planned:
:mod:`perfros_bag.export.planned`.
"""

from __future__ import annotations

import json
import math
import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import yaml

from perfros_bag.errors import InputError
from perfros_bag.fileio import atomic_write_text
from perfros_bag.system.names import NameKind, name_problem
from perfros_bag.system.plan import Plan
from perfros_bag.system.types import System

FORMATS = ("roslaunch", "ros2-params")
PLACEHOLDER_PACKAGE = "PACKAGE"
# system.yaml machines: keys -> roslaunch <machine> attributes
MACHINE_ATTRS = {"address": "address", "user": "user", "env_loader": "env-loader",
                 "ssh_port": "ssh-port", "password": "password", "default": "default"}


def rounded_value(plan: Plan, system: System | None, node: str) -> int | float | None:
    """The node's planned parameter value (9 significant digits), typed: as system.yaml's
    ``parameter.type`` says (``int`` rounded), else (no system, or its parameter says no type)
    an int when the value is integral: a plan holds 13.0 for a kernel size swept at 7 and 13,
    which a node reading an int parameter must get as 13. Both exports type values so
    (``export --launch`` then by space.yaml's values too, :func:`~perfros_bag.sweep.deploy.plan_run`)."""
    v = plan.nodes[node].value
    if v is None or not math.isfinite(v):
        return None
    v = float(f"{v:.9g}")  # a curve's inverse leaves bisection noise: 24.99999999301508 -> 25.0
    sn = system.node.get(node) if system is not None else None
    if sn is not None and sn.parameter is not None and sn.parameter.type is not None:
        return int(round(v)) if sn.parameter.type == "int" else float(v)
    return int(v) if float(v).is_integer() else float(v)


def _param_name(plan: Plan, system: System | None, node: str) -> str | None:
    launch = _launch(system, node)
    return launch.get("param") or plan.nodes[node].parameter


def _launch(system: System | None, node: str) -> dict[str, str]:
    if system is None or node not in system.node:
        return {}
    return dict(system.node[node].launch)


def address_arg(computer: str) -> str:
    """The launch argument holding a computer's address."""
    return re.sub(r"[^A-Za-z0-9_]", "_", computer) + "_address"


def comment(text: str) -> ET.Element[Any]:
    """An XML comment holding ``text`` as XML allows it (ElementTree writes comments as they
    are): no ``--`` (written ``- -``), no character XML 1.0 forbids, padded with spaces."""
    text = "".join(ch for ch in text if ch in "\t\n\r" or ord(ch) >= 0x20 and not 0xD800 <= ord(ch) <= 0xDFFF
                   and ch not in "\ufffe\uffff")
    while "--" in text:
        text = text.replace("--", "- -")
    return ET.Comment(f" {text} ")


def check_plan_names(plan: Plan, plan_path: str | None = None) -> None:
    """Raise an :class:`InputError` naming the first node, computer or parameter name of
    the plan that ROS cannot use, and the rule it breaks."""
    named: list[tuple[str, NameKind, str]] = [(f"computer {c!r}", NameKind.COMPUTER, c) for c in plan.computers]
    for name, pn in plan.nodes.items():
        named.append((f"node {name!r}", NameKind.NODE, name))
        named.append((f"node {name!r}: computer", NameKind.COMPUTER, pn.computer))
        if pn.parameter is not None:
            named.append((f"node {name!r}: parameter", NameKind.PARAMETER, pn.parameter))
    for where, kind, name in named:
        problem = name_problem(kind, name)
        if problem is not None:
            raise InputError(plan_path, f"{where}: {problem}")


def add_machines(root: ET.Element, plan: Plan, system: System | None) -> None:
    """One ``<machine>`` per computer of the plan: system.yaml's ``machines:`` attributes,
    else its address an ``<arg name="<computer>_address">`` defaulting to the computer's name."""
    machines = system.machines if system is not None else {}
    used = {n.computer for n in plan.nodes.values()}
    computers = list(plan.computers) + sorted(used - set(plan.computers))
    for c in computers:
        attrs = {MACHINE_ATTRS[k]: v for k, v in machines.get(c, {}).items() if k in MACHINE_ATTRS}
        if "address" not in attrs:
            arg = address_arg(c)
            ET.SubElement(root, "arg", {"name": arg, "default": c})
            attrs["address"] = f"$(arg {arg})"
        ET.SubElement(root, "machine", {"name": c, **attrs})


def roslaunch_xml(plan: Plan, system: System | None = None, *, plan_path: str | None = None) -> str:
    """The plan as a ROS 1 launch file (text)."""
    plan.require_feasible(plan_path, "export")
    check_plan_names(plan, plan_path)
    root = ET.Element("launch")
    root.append(comment(f"generated by perfros-bag: problem {plan.problem}, {len(plan.nodes)} nodes, "
                        f"{len(plan.computers)} computers"))
    root.append(comment("placeholders: a machine without an address in system.yaml (machines:) gets "
                        "the argument <computer>_address, defaulting to the computer's name; a node "
                        "without launch.package in system.yaml has pkg=\"" + PLACEHOLDER_PACKAGE
                        + "\" and type = its name"))
    add_machines(root, plan, system)
    for name, pn in plan.nodes.items():
        launch = _launch(system, name)
        attrs = {
            "name": launch.get("name", name),
            "pkg": launch.get("package", PLACEHOLDER_PACKAGE),
            "type": launch.get("type", name),
            "machine": pn.computer,
        }
        attrs.update(_nodelet_attrs(system, name, launch, standalone=pn.standalone))
        if "namespace" in launch:
            attrs["ns"] = launch["namespace"]
        el = ET.SubElement(root, "node", attrs)
        pname, value = _param_name(plan, system, name), rounded_value(plan, system, name)
        if pname is not None and value is not None:
            ET.SubElement(el, "param", {"name": pname, "type": "int" if isinstance(value, int) else "double",
                                        "value": str(value) if isinstance(value, int) else repr(value)})
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _ros_name(system: System | None, node: str) -> str:
    """A node's full ROS name: ``/namespace/name`` from its ``launch:``."""
    launch = _launch(system, node)
    return "/" + "/".join(p for p in (launch.get("namespace", "").strip("/"), launch.get("name", node)) if p)


def _nodelet_attrs(system: System | None, name: str, launch: dict[str, str], *,
                   standalone: bool = False) -> dict[str, str]:
    """ROS 1: a hosted node (``container:``) is its manager's nodelet, ``<node pkg="nodelet"
    type="nodelet" args="load LOOKUP /MANAGER">`` (LOOKUP: :func:`~perfros_bag.sweep.plugins.hosted_plugin`),
    or ``args="standalone LOOKUP"`` when the plan runs it ``standalone``; a container whose
    ``launch.package`` is unset or ``nodelet`` is a ``nodelet manager``."""
    if system is None or name not in system.node:
        return {}
    host = system.node[name].container
    if host is not None:
        from perfros_bag.sweep.plugins import hosted_plugin

        lookup = (hosted_plugin(launch["package"], launch.get("type"), name, ros2=False, source=system.source)
                  if "package" in launch else f"{PLACEHOLDER_PACKAGE}/{launch.get('type', name)}")
        args = f"standalone {lookup}" if standalone else f"load {lookup} {_ros_name(system, host)}"
        return {"pkg": "nodelet", "type": "nodelet", "args": args}
    if name in system.containers and launch.get("package", "nodelet") == "nodelet":
        return {"pkg": "nodelet", "type": "nodelet", "args": "manager"}
    return {}


def _ros2_key(system: System | None, node: str) -> str:
    launch = _launch(system, node)
    name = launch.get("name", node)
    ns = launch.get("namespace")
    if ns:
        return "/" + "/".join(part for part in (ns.strip("/"), name.strip("/")) if part)
    return name


def ros2_params(plan: Plan, system: System | None = None) -> dict[str, Any]:
    """``{node: {"ros__parameters": {param: value}}}`` for every plan node."""
    out: dict[str, Any] = {}
    for name in plan.nodes:
        params: dict[str, Any] = {}
        pname, value = _param_name(plan, system, name), rounded_value(plan, system, name)
        if pname is not None and value is not None:
            params[pname] = value
        out[_ros2_key(system, name)] = {"ros__parameters": params}
    return out


def ros2_params_yaml(plan: Plan, system: System | None = None, *, plan_path: str | None = None) -> str:
    """The ROS 2 parameters file with the placement table as leading comments."""
    plan.require_feasible(plan_path, "export")
    check_plan_names(plan, plan_path)
    lines = [f"# generated by perfros-bag: problem {plan.problem}, {len(plan.nodes)} nodes",
             "# placement (node -> computer): start each node on its computer"]
    for name, pn in plan.nodes.items():
        lines.append(f"# placement: {json.dumps(_ros2_key(system, name))} -> {json.dumps(pn.computer)}")
    body = yaml.safe_dump(ros2_params(plan, system), sort_keys=False, default_flow_style=False,
                          allow_unicode=True)
    return "\n".join(lines) + "\n" + body


def ros2_value(value: int | float) -> str:
    """A parameter value as ROS 2 XML launch infers its type (the ROS 2 launch migration
    guide: ``value="1"`` an integer, ``value="1.0"`` a float): a float always has a dot."""
    if isinstance(value, int):
        return str(value)
    text = repr(float(value))
    mantissa, e, exponent = text.partition("e")
    return text if "." in mantissa else f"{mantissa}.0{e}{exponent}"


def ros2_launch_path(out: str | Path, computer: str) -> Path:
    """Where the ROS 2 launch file of ``computer`` goes, beside the parameters file ``out``."""
    p = Path(out)
    stem = p.name[: -len(p.suffix)] if p.suffix else p.name
    return p.with_name(f"{stem}.{computer}.launch.xml")


def ros2_launch_xml(plan: Plan, system: System | None, computer: str) -> str:
    """A ROS 2 XML launch file starting the plan's nodes on ``computer``: ``<node pkg= exec=
    name= [namespace=]>`` with ``<param name= value=>`` (the ROS 2 launch documentation's
    format; no ``type`` or ``machine``: ROS 2 has neither). A container (a node others name as
    their system.yaml ``container``) is a ``<node_container pkg= exec= name= namespace=>``
    (default ``rclcpp_components``/``component_container``) holding a ``<composable_node pkg=
    plugin= name=>`` per hosted node (its C++ class: :func:`~perfros_bag.sweep.plugins.hosted_plugin`), as ROS 2's
    "Launching composable nodes" guide writes them; the plan keeps a container's nodes on its
    computer, but for one it runs ``standalone``: that one gets a ``component_container`` of its
    own (``NAME_container``) on its own computer."""
    from perfros_bag.sweep.plugins import hosted_plugin

    root = ET.Element("launch")
    root.append(comment(f"generated by perfros-bag: the plan's nodes on computer {computer} (problem "
                        f"{plan.problem}); a node without launch.package in system.yaml has pkg=\""
                        + PLACEHOLDER_PACKAGE + "\" and exec = its name"))
    containers = system.containers if system is not None else {}
    hosted = {m for members in containers.values() for m in members}

    def composable(el: ET.Element, member: str) -> None:
        mine = _launch(system, member)
        part = {"pkg": mine.get("package", PLACEHOLDER_PACKAGE),
                "plugin": hosted_plugin(mine.get("package"), mine.get("type"), member, ros2=True,
                                        source=system.source if system is not None else None),
                "name": mine.get("name", member)}
        if mine.get("namespace"):
            part["namespace"] = mine["namespace"]
        _ros2_param(ET.SubElement(el, "composable_node", part), plan, system, member)

    for name, pn in plan.nodes.items():
        if pn.computer != computer or name in hosted and not pn.standalone:
            continue
        launch = _launch(system, name)
        if name in hosted:  # run standalone: a container of its own holding it alone
            own = ET.SubElement(root, "node_container", {
                "pkg": "rclcpp_components", "exec": "component_container",
                "name": f"{launch.get('name', name)}_container", "namespace": launch.get("namespace", "")})
            composable(own, name)
            continue
        if name in containers:
            attrs = {"pkg": launch.get("package", "rclcpp_components"),
                     "exec": launch.get("type", "component_container"),
                     "name": launch.get("name", name), "namespace": launch.get("namespace", "")}
            el = ET.SubElement(root, "node_container", attrs)
            for member in containers[name]:
                if member in plan.nodes and not plan.nodes[member].standalone:
                    composable(el, member)
            _ros2_param(el, plan, system, name)
            continue
        attrs = {"pkg": launch.get("package", PLACEHOLDER_PACKAGE), "exec": launch.get("type", name),
                 "name": launch.get("name", name)}
        if launch.get("namespace"):
            attrs["namespace"] = launch["namespace"]
        _ros2_param(ET.SubElement(root, "node", attrs), plan, system, name)
    ET.indent(root, space="  ")
    return '<?xml version="1.0" encoding="utf-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _ros2_param(el: ET.Element, plan: Plan, system: System | None, name: str) -> None:
    """The node's planned value as a ``<param>`` of ``el`` (when it has one)."""
    pname, value = _param_name(plan, system, name), rounded_value(plan, system, name)
    if pname is not None and value is not None:
        ET.SubElement(el, "param", {"name": pname, "value": ros2_value(value)})


def ros2_launch_files(plan: Plan, system: System | None, out: str | Path) -> dict[Path, str]:
    """One ROS 2 launch file per computer that runs a node, beside the parameters file ``out``."""
    used = {pn.computer for pn in plan.nodes.values()}
    return {ros2_launch_path(out, c): ros2_launch_xml(plan, system, c)
            for c in [*plan.computers, *sorted(used - set(plan.computers))] if c in used}


def read_placement_comments(text: str) -> dict[str, str]:
    """The placement table of a file written by :func:`ros2_params_yaml`."""
    out: dict[str, str] = {}
    for line in text.splitlines():
        if line.startswith("# placement: "):
            node, _, comp = line[len("# placement: "):].partition(" -> ")
            out[json.loads(node)] = json.loads(comp)
    return out


def export_plan(plan_path: str | Path, fmt: str, out: str | Path, system_path: str | Path | None = None) -> str:
    """Read the plan (and system), write the export atomically; returns the text."""
    from perfros_bag.system.planfile import load_plan, plan_system

    if fmt not in FORMATS:
        raise InputError(None, f"unknown export format {fmt!r} (one of {', '.join(FORMATS)})")
    plan = load_plan(plan_path)
    system = plan_system(plan, plan_path, system_path)
    extra: dict[Path, str] = {}
    if fmt == "roslaunch":
        text = roslaunch_xml(plan, system, plan_path=str(plan_path))
    else:
        text = ros2_params_yaml(plan, system, plan_path=str(plan_path))
        extra = ros2_launch_files(plan, system, out)
    atomic_write_text(out, text)
    for path, launch in extra.items():
        atomic_write_text(path, launch)
    return text
