"""Each node's candidate choices for a solve (:func:`fixed_choices`: all of them for
Problem 1, the one fixed setting for Problem 2), and Problem 2's ``settings`` (node ->
CPU level) from parameter values (:func:`settings_from_values`), from a plan
(:func:`settings_from_plan`) or every node at its lowest (:func:`lowest_settings`).
"""

from __future__ import annotations

import dataclasses
import math
import warnings
from collections.abc import Mapping
from pathlib import Path

from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.system.plan import Plan
from perfros_bag.system.types import Choice, Node, Problem, System

__all__ = ["MAX_CHOICES", "ROUNDING_UNITS", "DrivenLevel", "check_resolution", "choice_count", "fixed_choices",
           "lowest_settings", "settings_from_plan", "settings_from_values"]


class DrivenLevel(float):
    """A driven node's Problem 2 CPU level that also names its own setting (an index into
    ``Node.settings``): two settings may need the same CPU at one input rate and still
    publish at different rates, so the level alone would not say which."""

    setting: int

    def __new__(cls, cpu: float, setting: int) -> DrivenLevel:
        level = super().__new__(cls, cpu)
        level.setting = setting
        return level


def _where(system: System) -> str | None:
    return system.source


def _match_cpu(system: System, node: Node, cpu: float, resolution: float) -> Choice:
    """The node's choice at CPU level ``cpu`` (a curve node off the grid gets a choice at
    exactly that level)."""
    choices = node.choices(resolution)
    for ch in choices:
        if math.isclose(ch.cpu, cpu, rel_tol=1e-9, abs_tol=1e-6):
            return ch
    if node.curve is not None:
        lo, hi = node.curve.domain
        if lo - 1e-6 <= cpu <= hi + 1e-6:
            return node.choice_at(0, min(max(cpu, lo), hi))
        raise InputError(_where(system), f"node {node.name!r}: setting CPU {cpu:g} "
                                         f"is outside its curve's range [{lo:g}, {hi:g}]")
    have = ", ".join(f"{c.cpu:g}" for c in choices)
    raise InputError(_where(system), f"node {node.name!r}: no setting with CPU {cpu:g} (its settings' CPU: {have})")


#: the most candidate choices (summed over the nodes) a solve may create. A curve node has
#: one choice per ``resolution`` CPU units of its domain; each choice costs the solvers time
#: and memory (measured, docs/formats.md: 23,500 choices solve exactly in ~17 s).
MAX_CHOICES = 100_000


def choice_count(system: System, resolution: float) -> int:
    """How many candidate choices the nodes have at ``resolution`` (computed, not built)."""
    total = 0
    for node in system.nodes:
        if node.curve is None:
            total += len(node.settings)
        else:
            lo, hi = node.curve.domain
            total += math.floor((hi - lo) / resolution + 1e-9) + 2
    return total


def check_resolution(system: System, resolution: float) -> None:
    """Raise an :class:`InputError` when ``resolution`` is not a finite number > 0 or would
    create more than :data:`MAX_CHOICES` choices."""
    if isinstance(resolution, bool) or not isinstance(resolution, int | float) or not math.isfinite(resolution) \
            or resolution <= 0:
        raise InputError(_where(system), f"resolution must be > 0, got {resolution!r}")
    count = choice_count(system, resolution)
    if count > MAX_CHOICES:
        widest = max((n for n in system.nodes if n.curve is not None),
                     key=lambda n: n.curve.domain[1] - n.curve.domain[0] if n.curve else 0.0)
        assert widest.curve is not None
        lo, hi = widest.curve.domain
        raise InputError(_where(system), f"resolution {resolution:g} gives {count:.3g} choices over the curves' CPU "
                                         f"ranges (node {widest.name!r}: [{lo:g}, {hi:g}]), more than the "
                                         f"{MAX_CHOICES:,} the solvers take: use a coarser resolution")


def fixed_choices(system: System, problem: Problem, settings: Mapping[str, float] | None = None,
                  resolution: float = 1.0, *, own: Mapping[str, int] | None = None) -> dict[str, list[Choice]]:
    """Each node's candidate choices, sorted by CPU: all of them for Problem 1; for Problem 2
    the single fixed one (``settings[node]`` as a CPU level, default the maximum-CPU choice).

    A driven node's choices are its settings at each input rate its input can take
    (:meth:`System.flow_choices`); for Problem 2 its CPU level is the one at its input's
    fixed rate, or ``own[node]`` names its setting (an index into ``Node.settings``)."""
    check_resolution(system, resolution)
    if settings:
        unknown = sorted(set(settings) - set(system.node))
        if unknown:
            raise InputError(_where(system), f"settings: unknown node(s) {', '.join(map(repr, unknown))}")
    out: dict[str, list[Choice]] = {}
    for node in system.nodes:
        if problem == Problem.PERFORMANCE or node.driven:  # a driven node's CPU follows its input: below
            out[node.name] = node.choices(resolution)
        elif settings and node.name in settings:
            out[node.name] = [_match_cpu(system, node, float(settings[node.name]), resolution)]
        else:
            out[node.name] = [node.choices(resolution)[-1]]
        if node.copy_cpu and not node.driven:  # run standalone: its copies on top (System.freed)
            out[node.name] = [dataclasses.replace(c, cpu=c.cpu + node.copy_cpu) for c in out[node.name]]
    if not system.has_flow:
        return out

    def fixed(name: str, options: list[Choice]) -> list[Choice]:
        """Problem 2: the driven node's one choice at its input's (fixed) rate: the one at
        ``settings[name]``'s CPU level, else its maximum-CPU one."""
        if own and name in own:
            return [c for c in options if c.setting == own[name]][:1]
        if settings and name in settings:
            given = settings[name]
            if isinstance(given, DrivenLevel):
                options = [c for c in options if c.setting == given.setting]
            level = float(given)
            match = [c for c in options if math.isclose(c.cpu, level, rel_tol=1e-9, abs_tol=1e-6)]
            if not match:
                have = ", ".join(f"{c.cpu:g}" for c in options)
                raise InputError(_where(system), f"node {name!r}: no setting with CPU {level:g} at its input's rate "
                                                 f"(its settings' CPU there: {have})")
            return match[:1]
        return [max(options, key=lambda c: (c.cpu, c.performance))]

    # Problem 1: counted on rates first, refused before a chain's choices multiply in memory
    out = system.flow_choices(out, fixed if problem == Problem.SERVER_CAPACITY else None, limit=MAX_CHOICES)
    total = sum(len(v) for v in out.values())
    if total > MAX_CHOICES:
        raise InputError(_where(system), f"the driven nodes' settings at every input rate their inputs can take give "
                                         f"{total:,} choices, more than the {MAX_CHOICES:,} the solvers take: use a "
                                         "coarser resolution or fewer settings upstream")
    return out


#: how far (CPU units) a setting's CPU may lie outside its curve's range without a warning:
#: ``perfros-bag fit`` rounds the range's ends inwards to whole units.
ROUNDING_UNITS = 1.0


def settings_from_values(system: System, values: Mapping[str, float], resolution: float = 1.0) -> dict[str, float]:
    """node -> parameter value  ==>  node -> CPU level: the choice or the setting with that
    value; else a curve node's fitted ``parameter->cpu`` relation evaluated at it.

    A curve node's level is clamped to its curve's CPU range, so that
    :func:`fixed_choices` always accepts it: a setting's measured CPU (or the fit's value)
    may lie just outside that range, which a fitted model narrows (whole CPU units, and
    where the performance fit leaves [0, max], see docs/formats.md). Beyond
    :data:`ROUNDING_UNITS` the clamp is reported with a :class:`PerfrosWarning`."""
    check_resolution(system, resolution)
    out: dict[str, float] = {}
    own: dict[str, int] = {}  # driven nodes: the setting with the value
    for name, v in values.items():
        node = system.node.get(name)
        if node is None:
            raise InputError(_where(system), f"settings: unknown node {name!r}")
        if not math.isfinite(v):
            raise InputError(_where(system), f"settings: node {name!r}: value {v!r} is not a finite number")
        if node.driven:
            own[name] = _setting_with_value(system, node, v)
            continue
        rel = node.relations.get("parameter->cpu")
        # a setting first (its own, measured CPU: on a fitted curve several CPU levels may
        # map back to the same end value), then the fitted relation, then a choice
        match = [s.cpu for s in node.settings
                 if s.value is not None and math.isclose(s.value, v, rel_tol=1e-9, abs_tol=1e-9)]
        if not (match or (rel is not None and node.curve is not None)):
            match = [c.cpu for c in node.choices(resolution)
                     if c.value is not None and math.isclose(c.value, v, rel_tol=1e-9, abs_tol=1e-9)]
        if match:
            cpu = match[0]
        elif rel is not None and node.curve is not None:
            plo, phi = rel.domain
            if not plo - 1e-9 <= v <= phi + 1e-9:
                raise InputError(_where(system), f"settings: node {name!r}: value {v:g} is outside its parameter's "
                                                 f"range [{plo:g}, {phi:g}]")
            cpu = rel(v)
        else:
            have = sorted({c.value for c in node.choices(resolution) if c.value is not None}
                          | {s.value for s in node.settings if s.value is not None})
            hint = (f"its values: {', '.join(f'{x:g}' for x in have)}" if have
                    else "it has no parameter values, only CPU levels")
            raise InputError(_where(system), f"settings: node {name!r} has no setting with value {v:g} ({hint})")
        if not math.isfinite(cpu):
            raise InputError(_where(system), f"settings: node {name!r}: value {v:g} gives no finite CPU level "
                                             f"(its parameter->cpu relation gives {cpu!r})")
        out[name] = _clamp(system, node, v, cpu)
    if own:  # a driven node's CPU level is its setting's at the rate its input then has
        fixed = fixed_choices(system, Problem.SERVER_CAPACITY, out, resolution, own=own)
        out.update({name: DrivenLevel(fixed[name][0].cpu, own[name]) for name in own})
    return out


def lowest_settings(system: System, resolution: float = 1.0) -> dict[str, float]:
    """node -> CPU level with every node at its least-CPU setting (a driven node's at the rate
    its input then has): Problem 2's ``settings`` for "everything at its lowest"."""
    base = {n.name: n.choices(resolution)[0].cpu for n in system.nodes if not n.driven}
    own = {n.name: _least_setting(n) for n in system.nodes if n.driven}
    fixed = fixed_choices(system, Problem.SERVER_CAPACITY, base, resolution, own=own)
    return {name: options[0].cpu for name, options in fixed.items()}


def _least_setting(node: Node) -> int:
    """A driven node's setting with the least CPU per input message (then base CPU)."""
    return min(range(len(node.settings)), key=lambda j: (node.settings[j].cpu_per_hz or 0.0, node.settings[j].cpu))


def _setting_with_value(system: System, node: Node, value: float) -> int:
    """The index of the driven node's setting with ``value``."""
    j = node.setting_index(value)
    if j is not None:
        return j
    have = ", ".join(f"{s.value:g}" for s in node.settings if s.value is not None) or "none"
    raise InputError(_where(system), f"settings: node {node.name!r} has no setting with value {value:g} "
                                     f"(its values: {have})")


def _clamp(system: System, node: Node, value: float, cpu: float) -> float:
    """``cpu`` clamped to the node's curve range (discrete nodes: unchanged)."""
    if node.curve is None:
        return cpu
    lo, hi = node.curve.domain
    clamped = min(max(cpu, lo), hi)
    if abs(clamped - cpu) > ROUNDING_UNITS + 1e-6:
        where = f"{_where(system)}: " if _where(system) else ""
        warnings.warn(f"{where}settings: node {node.name!r}: value {value:g} needs {cpu:.4g} CPU, outside its "
                      f"curve's range [{lo:g}, {hi:g}]: using {clamped:g}", PerfrosWarning, stacklevel=3)
    return clamped


def settings_from_plan(plan: Plan, system: System | None = None, resolution: float = 1.0) -> dict[str, float]:
    """node -> CPU level from a plan (e.g. Problem 1's answer fed to Problem 2): the plan's
    own CPU levels when ``system`` is the one the plan was solved from (or not given), less
    the fixed copy a node the plan runs standalone pays (:meth:`System.copy_charge`); for
    another model of the same nodes (e.g. one fitted with ``fit --cpu p95``), each node's
    parameter value in ``system`` (:func:`settings_from_values`), and a node without a value
    at its one choice there."""
    if system is None or _same_source(plan.system, system.source):
        levels: dict[str, float] = {name: n.cpu for name, n in plan.nodes.items()}
        if system is not None:
            for name, n in plan.nodes.items():
                node = system.node.get(name)
                if node is not None and node.driven and n.value is not None:  # its own setting too (by its value)
                    levels[name] = DrivenLevel(n.cpu, _setting_with_value(system, node, n.value))
                elif node is not None and n.standalone and (charge := system.copy_charge(name)) is not None:
                    levels[name] = n.cpu - charge[1]  # run standalone: its copy is on top of its setting's CPU
        return levels
    out = settings_from_values(system, {name: n.value for name, n in plan.nodes.items()
                                        if n.value is not None and name in system.node}, resolution)
    for name, n in plan.nodes.items():
        if name not in out and name in system.node:
            choices = system.node[name].choices(resolution)
            out[name] = choices[0].cpu if len(choices) == 1 else n.cpu
    return out


def _same_source(a: str | None, b: str | None) -> bool:
    """Do two recorded source paths name the same file (best effort)?"""
    if a is None or b is None:
        return a == b
    try:
        return Path(a).resolve() == Path(b).resolve()
    except OSError:
        return a == b
