"""The names ROS can run: nodes, topics, parameters, namespaces, packages, computers.

One copy of the rules, used wherever a name enters the tool or leaves it for a launch
file (system.yaml, a model.json's system, manifest.yaml, characterisation.csv, export).
system.yaml describes ROS 1 and ROS 2 systems alike, so:

- **node names** (and ``launch.name``) follow the rule both accept: a letter, then letters,
  digits and ``_`` (a ROS 1 *base name*, http://wiki.ros.org/Names, is also what a ROS 2
  node name may be, except that ROS 2 would also take a leading ``_``). A node name
  becomes a launch file's ``name=`` and, by default, its ``type=``: it must run on both.
- **topic, parameter and namespace names** must be valid ROS 1 graph resource names:
  the first character a letter, ``/`` or ``~``, then letters, digits, ``_`` and ``/``, no
  ``//``. ROS 2 (design.ros2.org, "Topic and Service name mapping") is stricter in four
  ways: no trailing ``/``, no ``__``, no token starting with a digit, ``~`` only as ``~``
  or ``~/...``. A name valid for ROS 1 but not ROS 2 is accepted with a warning
  (:func:`ros2_problem`): recordings of ROS 1 systems hold such names, and refusing them
  would refuse the system the recordings came from.
- **computer names** are roslaunch machine names that serve as the default host address:
  dot-separated labels of letters, digits, ``-`` and ``_``, each starting and ending
  with a letter or digit, at most 63 characters a label and 253 in all (RFC 1123 host
  names, plus ``_``, which machine names may hold; give such a computer an ``address``
  under ``machines:``).
- **packages**: a letter, then letters, digits, ``_`` and ``-`` (REP 144 and the legacy
  ROS 1 names); **executables** (``launch.type``): letters, digits, ``_ . + -``, not
  starting with ``.``.
- any other text written into a launch file (``machines:`` attributes) must hold no
  control characters (XML cannot hold most of them; :func:`text_problem`).

:func:`name_problem` says which rule a name breaks (None when it is valid); the caller
names the file and the entry.
"""

from __future__ import annotations

import ipaddress
import re
from enum import StrEnum


class NameKind(StrEnum):
    """What a name names (each kind has one rule)."""

    NODE = "node name"
    GRAPH_NODE = "ROS node graph name"  # a launched node's full name, e.g. /robot1/amcl
    TOPIC = "topic name"
    PARAMETER = "parameter name"
    NAMESPACE = "namespace"
    COMPUTER = "computer name"
    PACKAGE = "package name"
    EXECUTABLE = "executable name"
    PLUGIN = "plugin class name"  # a nodelet's / composable node's: pkg::Class or pkg/name


#: the longest name accepted (ROS 2 node names; host names are shorter, see the rule)
MAX_NAME_LENGTH = 255

_BASE = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
_GRAPH = re.compile(r"[~/A-Za-z][A-Za-z0-9_/]*")
_LABEL = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9_-]{0,61}[A-Za-z0-9])?")
_PACKAGE = re.compile(r"[A-Za-z][A-Za-z0-9_-]*")
_EXECUTABLE = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.+-]*")
_PLUGIN = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(?:::[A-Za-z_][A-Za-z0-9_]*)+"  # a C++ class
                     r"|[A-Za-z][A-Za-z0-9_-]*/[A-Za-z0-9_][A-Za-z0-9_.+-]*")  # a pluginlib lookup name
_SUBSTITUTION = re.compile(r"\$\((?:arg|env|optenv) [A-Za-z_][A-Za-z0-9_]*\)")
_RULES: dict[NameKind, str] = {
    NameKind.NODE: "a letter, then letters, digits and '_' (a ROS 1 base name, a ROS 2 node name)",
    NameKind.GRAPH_NODE: "ROS graph name: a letter, '/' or '~', then letters, digits, '_' and '/', no '//', "
                         "not ending with '/'",
    NameKind.TOPIC: "ROS graph name: a letter, '/' or '~', then letters, digits, '_' and '/', no '//'",
    NameKind.PARAMETER: "ROS graph name: a letter, '/' or '~', then letters, digits, '_' and '/', no '//'",
    NameKind.NAMESPACE: "ROS graph name: a letter, '/' or '~', then letters, digits, '_' and '/', no '//'",
    NameKind.COMPUTER: "roslaunch machine / host name: dot-separated labels of letters, digits, '-' and '_', "
                       "each starting and ending with a letter or digit, at most 63 characters",
    NameKind.PACKAGE: "a letter, then letters, digits, '_' and '-'",
    NameKind.EXECUTABLE: "letters, digits, '_', '.', '+' and '-', not starting with '.'",
    NameKind.PLUGIN: "a C++ class name (identifiers joined by '::', e.g. opencv_apps::PeopleDetectNodelet) or a "
                     "pluginlib lookup name (PACKAGE/NAME, e.g. opencv_apps/people_detect)",
}


def rule(kind: NameKind) -> str:
    """The rule a name of ``kind`` follows, in words."""
    return _RULES[kind]


def text_problem(text: str) -> str | None:
    """A control character in ``text`` (a launch file cannot carry it), or None."""
    for ch in text:
        if ord(ch) < 0x20 or 0x7F <= ord(ch) < 0xA0 or ch in "\ufffe\uffff" or 0xD800 <= ord(ch) < 0xE000:
            return f"holds the control character {ch!r}"
    return None


def name_problem(kind: NameKind, name: object) -> str | None:
    """Why ``name`` is not a valid name of ``kind`` (the character or part at fault and the
    rule), or None when it is valid. For topics, parameters and namespaces this is the
    ROS 1 rule; :func:`ros2_problem` adds ROS 2's."""
    if not isinstance(name, str) or not name:
        return f"is not a valid {kind}: must be a non-empty string ({rule(kind)})"
    if len(name) > MAX_NAME_LENGTH:
        return f"is not a valid {kind}: longer than {MAX_NAME_LENGTH} characters"
    control = text_problem(name)
    if control is not None:
        return f"is not a valid {kind}: {control}"
    if kind == NameKind.COMPUTER:
        ok = len(name) <= 253 and all(_LABEL.fullmatch(label) for label in name.split("."))
    elif kind == NameKind.NODE:
        ok = _BASE.fullmatch(name) is not None
    elif kind == NameKind.PACKAGE:
        ok = _PACKAGE.fullmatch(name) is not None
    elif kind == NameKind.EXECUTABLE:
        ok = _EXECUTABLE.fullmatch(name) is not None
    elif kind == NameKind.PLUGIN:
        ok = _PLUGIN.fullmatch(name) is not None
    else:
        ok = _GRAPH.fullmatch(name) is not None and "//" not in name
        if kind == NameKind.GRAPH_NODE:
            ok = ok and not name.endswith("/") and "~" not in name
    if ok:
        return None
    return f"is not a valid {kind}{_first_bad(kind, name)} ({rule(kind)})"


def system_node_name(ros_name: str) -> str:
    """A ROS node's name as system.yaml and manifest.yaml name it: the graph name without
    its leading slash, namespaces joined by ``_`` (``/robot1/amcl`` -> ``robot1_amcl``), so
    it is a valid :attr:`NameKind.NODE` name whenever the ROS name is a valid graph name."""
    return ros_name.strip("/").replace("/", "_")


def _first_bad(kind: NameKind, name: str) -> str:
    allowed = {NameKind.NODE: "_", NameKind.PACKAGE: "_-", NameKind.EXECUTABLE: "_.+-", NameKind.PLUGIN: "_.+-:/",
               NameKind.COMPUTER: "_-."}.get(kind, "_/~")
    for i, ch in enumerate(name):
        if not (ch.isascii() and (ch.isalnum() or ch in allowed)):
            return f": character {ch!r} at position {i + 1}"
    return ""


def ros2_problem(kind: NameKind, name: str) -> str | None:
    """The ROS 2 topic-name rule a (ROS 1 valid) topic, parameter or namespace name breaks,
    or None. Other kinds have one rule for both and give None."""
    if kind not in (NameKind.TOPIC, NameKind.PARAMETER, NameKind.NAMESPACE):
        return None
    if len(name) > 1 and name.endswith("/"):
        return "ends with '/'"
    if "__" in name:
        return "holds '__'"
    if name.startswith("~") and len(name) > 1 and name[1] != "/":
        return "'~' must be followed by '/'"
    for token in name.lstrip("~").split("/"):
        if token[:1].isdigit():
            return f"token {token!r} starts with a digit"
    return None


def address_problem(address: str) -> str | None:
    """Why ``address`` is not a host name, an IP address or a roslaunch substitution giving
    one (``$(arg NAME)``, ``$(env NAME)``, ``$(optenv NAME)``), or None."""
    if _SUBSTITUTION.fullmatch(address):
        return None
    try:
        ipaddress.ip_address(address)
        return None
    except ValueError:
        pass
    labels = address.split(".")
    if len(address) <= 253 and all(re.fullmatch(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?", x) for x in labels):
        return None
    return ("is not a host name or IP address (dot-separated labels of letters, digits and '-'), "
            "nor a roslaunch $(arg NAME) / $(env NAME) / $(optenv NAME)")
