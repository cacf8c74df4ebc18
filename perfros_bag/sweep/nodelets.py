"""Nodelets: which process hosts which node (docs/formats.md, "Nodelets").

A ROS 1 nodelet runs inside a manager process (``nodelet manager``); the launch file starts
it with a loader, ``nodelet load PKG/TYPE MANAGER``, a process of its own that registers
under the nodelet's name, asks the manager to load it and then only keeps a bond
(``/MANAGER/bond``) with it. The nodelet's topics are published and subscribed by the
manager's ROS node. ``nodelet standalone PKG/TYPE`` runs the nodelet in a process of its own.

:func:`nodelets_of` reads the membership from roslaunch's own resolution of the launch file
(:func:`perfros_bag.sweep.launchfile.resolve_launch`); :func:`with_membership` gives each
nodelet, in the graph the master saw, its container and the topics the manager carries for
it: those under the nodelet's own name (``/people/found``) and those its ``<remap>``s name
(``image`` -> ``/camera/image_raw``).
"""

from __future__ import annotations

import re
import shlex
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

from perfros_bag.errors import InputError
from perfros_bag.sweep.plugins import class_problem, package_dir

if TYPE_CHECKING:
    from pathlib import Path

    from perfros_bag.sweep.graph import Graph
    from perfros_bag.sweep.launchfile import Resolved, ResolvedNode

#: The message package of a nodelet's bond with its manager: never a node's output.
BOND_TYPE_PREFIX = "bond/"


@dataclass(frozen=True)
class Nodelet:
    """One ``nodelet load`` of the launch file."""

    name: str  # the nodelet's (and its loader's) full ROS name
    type: str  # PKG/TYPE
    manager: str  # the manager's full ROS name
    topics: tuple[str, ...]  # the targets of its <remap>s, resolved


def resolve_name(name: str, namespace: str) -> str:
    """A ROS name as a node in ``namespace`` resolves it (``~`` private names aside)."""
    if name.startswith("/"):
        return name
    return namespace.rstrip("/") + "/" + name


def _words(node: ResolvedNode) -> list[str]:
    try:
        return shlex.split(node.args)
    except ValueError:
        return node.args.split()


def is_nodelet_tool(node: ResolvedNode) -> bool:
    return node.package == "nodelet" and node.type == "nodelet"


def nodelets_of(resolved: Resolved) -> dict[str, Nodelet]:
    """Every ``nodelet load`` of the resolved launch file, by the nodelet's full name."""
    out: dict[str, Nodelet] = {}
    for n in resolved.nodes:
        if not is_nodelet_tool(n):
            continue
        words = [w for w in _words(n) if ":=" not in w]
        if len(words) >= 3 and words[0] == "load":
            topics = tuple(resolve_name(to, n.namespace) for _, to in n.remaps)
            out[n.full_name] = Nodelet(n.full_name, words[1], resolve_name(words[2], n.namespace), topics)
    return out


def managers_of(resolved: Resolved) -> set[str]:
    """The full names of the launch file's ``nodelet manager`` nodes."""
    return {n.full_name for n in resolved.nodes if is_nodelet_tool(n) and _words(n)[:1] == ["manager"]}


def check_nodelets(resolved: Resolved, path: Path | str | None, *, elsewhere: bool = False) -> dict[str, Nodelet]:
    """The launch file's nodelets, each loaded into a manager it starts and of a type its
    package exports (its package.xml's nodelet plugin description, read as pluginlib reads
    it: :mod:`perfros_bag.sweep.plugins`): otherwise one :class:`InputError`. ``elsewhere``:
    the file runs on other machines (``export --launch``), so a package not installed here is
    a warning, not an error."""
    nodelets = nodelets_of(resolved)
    if not nodelets:
        return nodelets
    managers = managers_of(resolved)
    for n in nodelets.values():
        if n.manager not in managers:
            started = ", ".join(sorted(managers)) or "none"
            raise InputError(path, f"node {n.name}: nodelet load {n.type} into manager {n.manager}, which the "
                             f"launch file never starts (its nodelet managers: {started})")
    for n in nodelets.values():
        pkg = re.split(r"/|::", n.type, maxsplit=1)[0]
        if elsewhere and package_dir(pkg) is None:
            import warnings

            from perfros_bag.errors import PerfrosWarning

            warnings.warn(PerfrosWarning(f"{path}: node {n.name}: class {n.type} not checked: package {pkg} is not "
                                         "installed here"), stacklevel=2)
            continue
        problem = class_problem(pkg, n.type, by_type=False)
        if problem is not None:
            raise InputError(path, f"node {n.name}: class {n.type} does not exist: {problem}")
    return nodelets


def check_plan_membership(nodelets: Mapping[str, Nodelet], where: Mapping[str, str],
                          plan_path: Path | str | None, standalone: Iterable[str] = ()) -> None:
    """Each nodelet the launch file loads on the computer the plan gives its manager
    (``where``: system.yaml node name -> computer): the launch file fixes the membership, so
    a plan that splits them is one :class:`InputError` naming the plan, both nodes and the
    manager. A nodelet the plan runs in a process of its own (``standalone``: system.yaml
    names, plan.json ``standalone: true``) may sit anywhere: it is not loaded."""
    from perfros_bag.system.names import system_node_name

    alone = set(standalone)
    for n in nodelets.values():
        mine, host = system_node_name(n.name), system_node_name(n.manager)
        if mine in alone:
            continue
        if mine in where and host in where and where[mine] != where[host]:
            raise InputError(plan_path, f"container {host}: node {mine} on {where[mine]} but its container {host} on "
                                        f"{where[host]}; the launch file loads {mine} into {n.manager} "
                                        f"(nodelet load {n.type}), so they share a computer unless the plan runs "
                                        f"{mine} standalone (system.yaml membership: choose)")


def standalone_nodelets(nodelets: Mapping[str, Nodelet], standalone: Iterable[str],
                        source: Path | str | None = None) -> tuple[str, ...]:
    """The full ROS names of the launch file's nodelets whose system.yaml names are in
    ``standalone`` (a plan's nodes with ``standalone: true``), sorted: what runs as
    ``nodelet standalone`` (:func:`standalone_argv`). A plan node that the launch file does
    not load as a nodelet is run as the file starts it (a process of its own already, or not
    started at all): a warning names it, prefixed with ``source``, since the plan meant to
    take it out of a container the launch file does not put it in (check_plan_membership
    likewise lets a standalone node sit anywhere rather than refuse it)."""
    from perfros_bag.system.names import system_node_name

    alone = set(standalone)
    plain = sorted(alone - {system_node_name(n) for n in nodelets})
    if plain:
        import warnings

        from perfros_bag.errors import PerfrosWarning

        warnings.warn(PerfrosWarning(
            f"{source or 'the plan'}: node(s) {', '.join(plain)}: the plan runs them standalone, but the launch file "
            "does not load them as nodelets (nodelet load): run as the launch file starts them"), stacklevel=2)
    return tuple(sorted(n for n in nodelets if system_node_name(n) in alone))


def with_membership(graph: Graph, nodelets: Mapping[str, Nodelet]) -> Graph:
    """``graph`` with each nodelet's ``container`` and ``nodelet`` type, and the topics its
    manager carries for it given to the nodelet (the manager keeps the rest)."""
    if not nodelets:
        return graph
    nodes = tuple(replace(n, container=nodelets[n.name].manager, nodelet=nodelets[n.name].type)
                  if n.name in nodelets else n for n in graph.nodes)
    by_manager: dict[str, list[Nodelet]] = {}
    for n in nodelets.values():
        by_manager.setdefault(n.manager, []).append(n)
    topics = []
    for t in graph.topics:
        if not (t.type or "").startswith(BOND_TYPE_PREFIX):
            t = replace(t, publishers=_owners(t.name, t.publishers, by_manager),
                        subscribers=_owners(t.name, t.subscribers, by_manager))
        topics.append(t)
    return replace(graph, nodes=nodes, topics=tuple(topics))


def _owners(topic: str, who: Sequence[str], by_manager: Mapping[str, list[Nodelet]]) -> tuple[str, ...]:
    out: set[str] = set()
    for w in who:
        mine = [n.name for n in by_manager.get(w, ()) if topic.startswith(n.name + "/") or topic in n.topics]
        out.update(mine or [w])
    return tuple(sorted(out))


def standalone_argv(argv: Sequence[str]) -> list[str]:
    """A loader's command line (``nodelet load PKG/TYPE MANAGER ...``) as ``nodelet
    standalone PKG/TYPE ...``: the same nodelet in a process of its own."""
    words = list(argv)
    i = next((k for k, w in enumerate(words) if w == "load"), None)
    if i is None or i + 2 >= len(words):
        raise InputError(None, f"not a nodelet loader's command line: {' '.join(words)}")
    return [*words[:i], "standalone", words[i + 1], *words[i + 3:]]
