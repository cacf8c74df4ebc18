"""The plugin classes a ROS 1 package exports, read as pluginlib reads them
(docs/formats.md, "Nodelets").

pluginlib finds a package's plugins through its manifest: ``package.xml``'s
``<export><nodelet plugin="${prefix}/nodelet_plugins.xml"/></export>`` (the tag is the base
class's package, ``nodelet`` for nodelets; ``${prefix}`` the package's folder), then the
plugin description it names: ``<library path=...>`` (or several inside
``<class_libraries>``) holding ``<class name="LOOKUP" type="C++::Class"
base_class_type=...>``. A class's lookup name (what ``nodelet load`` takes) is its ``name``,
or its ``type`` when it has no ``name``. A ROS 2 composable node names the C++ class
(``ComposableNode(plugin="pkg::Class")``).

The package's folder: the first ``ROS_PACKAGE_PATH`` entry that is the package or holds it
(up to three levels down, as a catkin workspace's ``src/`` does), else ``share/PKG`` under
each ``CMAKE_PREFIX_PATH`` entry, else Debian's ``/usr/share/PKG``.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

SYSTEM_SHARE = Path("/usr/share")


@dataclass(frozen=True)
class PluginClass:
    """One ``<class>`` of a package's plugin description."""

    name: str  # the lookup name (``nodelet load`` takes it)
    type: str  # the C++ class (a ROS 2 composable node's ``plugin``)
    package: str
    description: Path  # the plugin description file it came from


def _manifest_name(path: Path) -> str | None:
    try:
        root = ET.parse(path).getroot()  # noqa: S314 - an installed package's own manifest
    except (ET.ParseError, OSError):
        return None
    el = root.find("name")
    return el.text.strip() if el is not None and el.text else None


def package_dir(package: str, env: Mapping[str, str] | None = None) -> Path | None:
    """The folder of ROS package ``package`` (the one holding its ``package.xml``), or None."""
    env = os.environ if env is None else env
    for entry in (env.get("ROS_PACKAGE_PATH") or "").split(os.pathsep):
        if not entry:
            continue
        root = Path(entry)
        for depth in range(4):
            for manifest in sorted(root.glob("/".join(["*"] * depth + ["package.xml"]))):
                if _manifest_name(manifest) == package:
                    return manifest.parent
    prefixes = [Path(p) / "share" for p in (env.get("CMAKE_PREFIX_PATH") or "").split(os.pathsep) if p]
    for share in [*prefixes, SYSTEM_SHARE]:
        if (share / package / "package.xml").is_file() and _manifest_name(share / package / "package.xml") == package:
            return share / package
    return None


def plugin_descriptions(folder: Path, base_package: str = "nodelet") -> list[Path]:
    """The plugin description files the package in ``folder`` exports for ``base_package``."""
    try:
        root = ET.parse(folder / "package.xml").getroot()  # noqa: S314 - an installed package's own manifest
    except (ET.ParseError, OSError):
        return []
    out = []
    for export in root.iter("export"):
        for el in export.iter(base_package):
            plugin = el.get("plugin")
            if plugin:
                out.append(Path(plugin.replace("${prefix}", str(folder))))
    return out


def exported_classes(package: str, base_package: str = "nodelet",
                     env: Mapping[str, str] | None = None) -> list[PluginClass] | None:
    """Every class ``package`` exports for ``base_package`` (pluginlib's reading of its
    manifest and plugin descriptions); None: no such package here."""
    folder = package_dir(package, env)
    if folder is None:
        return None
    out: list[PluginClass] = []
    for path in plugin_descriptions(folder, base_package):
        try:
            root = ET.parse(path).getroot()  # noqa: S314 - an installed package's plugin description
        except (ET.ParseError, OSError):
            continue
        for el in root.iter("class"):
            kind = el.get("type")
            name = el.get("name") or kind
            if name and kind:
                out.append(PluginClass(name, kind, package, path))
    return out


def find_class(classes: list[PluginClass], wanted: str, by_type: bool = True) -> PluginClass | None:
    """The class ``wanted`` names: by lookup name, else by C++ class name (then the lookup
    name under the class's own package first: opencv_apps declares each class twice,
    ``opencv_apps/smoothing`` and the older ``smoothing/smoothing``)."""
    named = next((c for c in classes if c.name == wanted), None)
    if named is not None or not by_type:
        return named
    typed = [c for c in classes if c.type == wanted]
    return next((c for c in typed if c.name.startswith(c.package + "/")), typed[0] if typed else None)


def all_exported_classes(base_package: str = "nodelet") -> list[PluginClass]:
    """Every class any installed package exports for ``base_package``: the packages
    ``rospack plugins --attrib=plugin BASE`` lists (the crawl pluginlib itself asks rospack
    for), each read by :func:`exported_classes`; empty when rospack is missing."""
    import shutil
    import subprocess

    rospack = shutil.which("rospack")
    if rospack is None:
        return []
    try:
        done = subprocess.run([rospack, "plugins", "--attrib=plugin", base_package], capture_output=True,
                              text=True, timeout=30, check=False)
    except (OSError, subprocess.TimeoutExpired):
        return []
    packages = dict.fromkeys(line.split(None, 1)[0] for line in done.stdout.splitlines() if line.strip())
    return [c for p in packages for c in exported_classes(p, base_package) or ()]


def resolve_class(package: str, wanted: str, env: Mapping[str, str] | None = None, *,
                  by_type: bool = True) -> PluginClass | str:
    """The nodelet class ``wanted`` (a lookup name or, with ``by_type``, a C++ class name)
    of ``package``, or why there is none (one sentence). Looked for in ``package``'s own
    plugin description first, then, as pluginlib does, in every package that exports
    nodelets. ``nodelet load`` takes only the lookup name (pluginlib refuses a C++ class
    name there: "the class ... does not exist")."""
    classes = exported_classes(package, env=env)
    found = find_class(classes or [], wanted, by_type)
    if found is None:
        found = find_class(all_exported_classes(), wanted, by_type)
    if found is not None:
        return found
    if not by_type:
        typed = find_class(classes or [], wanted) or find_class(all_exported_classes(), wanted)
        if typed is not None:
            return (f"{wanted} is a C++ class name; nodelet load takes its lookup name {typed.name} "
                    f"({typed.description})")
    if classes is None:
        return f"package {package} is not installed here (no package.xml found for it)"
    if not classes:
        return f"package {package} exports no nodelet (its package.xml has no <export><nodelet plugin=...>)"
    own = sorted(c.name for c in classes if c.name.startswith(package + "/")) or sorted(c.name for c in classes)
    return f"package {package} exports no such nodelet (its nodelets: {', '.join(own)})"


def class_problem(package: str, wanted: str, env: Mapping[str, str] | None = None, *,
                  by_type: bool = True) -> str | None:
    """Why ``wanted`` is not a nodelet class (one sentence), or None."""
    found = resolve_class(package, wanted, env, by_type=by_type)
    return found if isinstance(found, str) else None


def hosted_plugin(package: str | None, kind: str | None, node: str, *, ros2: bool,
                  source: str | Path | None = None) -> str:
    """What loads a hosted node (system.yaml ``container:``) whose ``launch`` gives
    ``package`` and ``type`` = ``kind``: the lookup name ``nodelet load`` takes (ROS 1), or
    the C++ class a ROS 2 ``<composable_node plugin=...>`` names (``ros2``). ``kind`` may be
    either of those (``opencv_apps/people_detect``, ``opencv_apps::PeopleDetectNodelet``) or an
    executable's name (``people_detect``: ``PACKAGE/people_detect`` is tried); each is
    resolved through the package's plugin description (:func:`resolve_class`). What cannot
    be resolved here is written as given with a warning, except where the other form cannot
    be guessed: an :class:`~perfros_bag.errors.InputError` naming ``source`` and the node."""
    import warnings

    from perfros_bag.errors import InputError, PerfrosWarning

    if package is None:
        return kind or node
    kind = kind or node
    plugin_form = "::" in kind or "/" in kind
    candidates = [kind] if plugin_form else [f"{package}/{kind}", kind]
    why = ""
    for c in candidates:
        found = resolve_class(package, c)
        if not isinstance(found, str):
            return found.type if ros2 else found.name
        why = why or found
    if ros2 and "::" in kind:
        return kind  # a ROS 2 class: its package need not be a ROS 1 one installed here
    if "::" in kind or (ros2 and plugin_form):
        want = "the C++ class a ROS 2 composable node names" if ros2 else "the lookup name nodelet load takes"
        other = "PKG::Class" if ros2 else "PKG/NAME"
        raise InputError(source, f"node {node!r}: launch.type {kind!r}: cannot tell {want}: {why}; give launch.type "
                                 f"as {other}")
    written = kind if ros2 or plugin_form else f"{package}/{kind}"
    warnings.warn(PerfrosWarning(f"node {node}: launch.type {kind!r} is no nodelet class found here ({why}): "
                                 f"written as {written!r}"), stacklevel=2)
    return written
