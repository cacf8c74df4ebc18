"""``manifest.yaml``: which recordings to characterise, with their CPU trace, computer and
settings (design.md contract)::

    system: ../system.yaml           # optional
    recordings:
      - path: tracker_f10.bag        # file or rosbag2 directory, relative to the manifest
        cpu: tracker_f10.cpu.csv     # optional; default <stem>.cpu.csv when it exists
        computer: robot1             # where it was measured (whose capacity normalises the
                                     #   CPU trace when units_per_core is not given)
        units_per_core: 100          # optional: CPU units of one busy core of that machine
        settings: {tracker1: 10}     # node -> parameter value in this run
        speed_factor: 1.02           # optional: the machine's speed during the run
                                     #   (perfros_bag.cpu.speed; recorded, never applied)

``units_per_core`` fixes the scale of the measurement itself (``sweep`` writes
:data:`SWEEP_UNITS_PER_CORE`): the trace is then normalised as ``cpu_percent / 100 x
units_per_core`` whatever a system.yaml says about the computers, so describing the robot
differently (its ``capacity``) changes the plan, never the data.

Node and computer names follow ROS's rules (:mod:`perfros_bag.system.names`). Structural
problems are :class:`InputError` naming the manifest and the entry; a missing
recording file is left to the per-recording work (one bad recording must not stop the rest).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.doccheck import Doc
from perfros_bag.fileio import MANIFEST_KIND, expect_kind, read_yaml
from perfros_bag.limits import number_problem
from perfros_bag.system.names import NameKind, name_problem

TOP_KEYS = {"system", "recordings"}
ENTRY_KEYS = {"path", "cpu", "computer", "units_per_core", "settings", "speed_factor", "standalone"}
#: The scale ``sweep`` records its runs in (and ``init`` drafts this machine with): 100 CPU
#: units = one busy core of the machine the sweep ran on.
SWEEP_UNITS_PER_CORE = 100

SettingValue = int | float | str


@dataclass(frozen=True)
class RecordingEntry:
    """One recording to characterise (resolved paths), from a manifest or from discovery."""

    path: Path
    name: str  # how the recording is named in the output (path relative to the manifest/DIR)
    cpu: Path | None = None  # the CPU trace; None: no trace
    computer: str | None = None
    settings: Mapping[str, SettingValue] = field(default_factory=dict)
    units_per_core: float | None = None  # the measurement's own scale; None: the computer's capacity
    speed_factor: float | None = None  # the machine's speed in this run (perfros_bag.cpu.speed); None: unknown
    #: nodelets that ran standalone in this run instead of in their manager (system.yaml names)
    standalone: tuple[str, ...] = ()


@dataclass(frozen=True)
class Manifest:
    path: Path
    system: Path | None
    recordings: tuple[RecordingEntry, ...]


def recording_stem(path: Path) -> str:
    """``run.bag`` -> ``run``; a rosbag2 directory ``run/`` -> ``run``."""
    return path.name if path.is_dir() else path.stem


def default_cpu_path(recording: Path) -> Path | None:
    """``<stem>.cpu.csv`` beside the recording (or inside a rosbag2 directory) when it exists."""
    stem = recording_stem(recording)
    candidates = [recording.parent / f"{stem}.cpu.csv"]
    if recording.is_dir():
        candidates.append(recording / f"{stem}.cpu.csv")
    return next((c for c in candidates if c.is_file()), None)


def write_manifest(path: str | Path, entries: list[dict[str, Any]], system: str | None = None) -> None:
    """Write a manifest (atomically) from plain entries (``path``, ``cpu``, ``computer``,
    ``settings``), checking them with the reader first: a bad entry is never written."""
    import yaml

    from perfros_bag.fileio import atomic_write_text

    doc: dict[str, Any] = {} if system is None else {"system": system}
    doc["recordings"] = entries
    parse_manifest(doc, Path(path))
    atomic_write_text(path, yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100))


def load_manifest(path: str | Path) -> Manifest:
    p = Path(path)
    data = read_yaml(p)
    return parse_manifest(data, p)


def parse_manifest(data: Any, path: Path) -> Manifest:
    doc = Doc(path)
    fail = doc.fail
    if data is None:
        raise fail("", "the manifest is empty (expected 'recordings:')")
    expect_kind(path, data, MANIFEST_KIND, {MANIFEST_KIND})
    doc.mapping(data, "", TOP_KEYS, expected="a mapping with 'recordings:'", got=type(data).__name__)
    base = path.parent
    system: Path | None = None
    if data.get("system") is not None:
        if not isinstance(data["system"], str) or not data["system"].strip():
            raise fail("system", f"must be a path, got {data['system']!r}")
        system = base / data["system"]
    raw = data.get("recordings")
    if raw is None:
        raise fail("", "missing 'recordings:' (a list of {path, cpu, computer, settings})")
    if not isinstance(raw, list):
        raise fail("recordings", f"must be a list, got {type(raw).__name__}")
    entries: list[RecordingEntry] = []
    seen: set[str] = set()
    for i, item in enumerate(raw):
        where = f"recordings[{i}]"
        if isinstance(item, str):
            item = {"path": item}
        doc.mapping(item, where, ENTRY_KEYS, expected="a mapping with 'path:'", got=type(item).__name__)
        rel = item.get("path")
        if not isinstance(rel, str) or not rel.strip():
            raise fail(f"{where}.path", f"must be a file or directory name, got {rel!r}")
        if rel in seen:
            raise fail(f"{where}.path", f"{rel!r} is listed twice")
        seen.add(rel)
        rec = base / rel
        cpu: Path | None
        if item.get("cpu") is not None:
            if not isinstance(item["cpu"], str) or not item["cpu"].strip():
                raise fail(f"{where}.cpu", f"must be a path, got {item['cpu']!r}")
            cpu = base / item["cpu"]
        else:
            cpu = default_cpu_path(rec)
        computer = item.get("computer")
        if computer is not None and (not isinstance(computer, str) or not computer.strip()):
            raise fail(f"{where}.computer", f"must be a computer's name, got {computer!r}")
        if computer is not None and name_problem(NameKind.COMPUTER, computer) is not None:
            raise fail(f"{where}.computer", f"{computer!r} {name_problem(NameKind.COMPUTER, computer)}")
        settings = _settings(item.get("settings"), f"{where}.settings", fail)
        units = item.get("units_per_core")
        if units is not None:
            problem = number_problem(units, positive=True)
            if problem is not None:
                raise fail(f"{where}.units_per_core", problem)
            units = float(units)
        speed = item.get("speed_factor")
        if speed is not None:
            from perfros_bag.cpu.speed import speed_problem

            problem = speed_problem(speed)
            if problem is not None:
                raise fail(f"{where}.speed_factor", problem)
            speed = float(speed)
        alone = item.get("standalone") or []
        if not isinstance(alone, list) or not all(isinstance(x, str) and x for x in alone):
            raise fail(f"{where}.standalone", f"must be a list of node names, got {alone!r}")
        entries.append(RecordingEntry(rec, rel, cpu, computer, settings, units, speed, tuple(alone)))
    return Manifest(path, system, tuple(entries))


def _settings(raw: Any, where: str, fail: Any) -> dict[str, SettingValue]:
    if raw is None:
        return {}
    if not isinstance(raw, Mapping):
        raise fail(where, f"must be a mapping node -> value, got {type(raw).__name__}")
    out: dict[str, SettingValue] = {}
    for node, value in raw.items():
        if not isinstance(node, str) or not node:
            raise fail(where, f"node names must be strings, got {node!r}")
        problem = name_problem(NameKind.NODE, node)
        if problem is not None:
            raise fail(where, f"{node!r} {problem}")
        if isinstance(value, bool) or value is None:
            raise fail(f"{where}.{node}", f"must be a number or a string, got {value!r}")
        if isinstance(value, int | float):
            if not math.isfinite(float(value)):
                raise fail(f"{where}.{node}", f"must be finite, got {value!r}")
            out[node] = int(value) if isinstance(value, int) else float(value)
        elif isinstance(value, str):
            out[node] = value
        else:
            raise fail(f"{where}.{node}", f"must be a number or a string, got {type(value).__name__}")
    return out
