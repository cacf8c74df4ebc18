"""Measured headroom: the CPU a node may need beyond the model's prediction (docs/solvers.md,
"Headroom").

``fit`` writes each setting's error (:mod:`perfros_bag.fitting.cpu_error`); ``solve
--headroom auto`` keeps it free (:func:`perfros_bag.solver.solve`). Both take the floor and
the rule that turns a setting's error into a solver choice's from here, so the rule lives in
one place:

- a setting of a node without ``input``: ``cpu_error``, CPU units beyond its ``cpu``;
- a driven node's setting: ``cpu_error_share``, the error as a share of its CPU at the input
  rate it was measured at; at any input rate its error is that share of its CPU there;
- a node with a CPU -> performance ``curve``: a CPU level between two of its settings carries
  the straight line between their ``cpu_error`` (by CPU; the end setting's beyond the ends)
  plus the node's ``cpu_error_between`` (``fit``: the parameter -> CPU fit's leave-one-out
  RMSE), a level at a setting's CPU that setting's ``cpu_error``;
- every choice at least :data:`FAIR_SHARE` x its CPU.
"""

from __future__ import annotations

import math

from perfros_bag.system.types import Choice, Node, Setting, System

#: the least share of its CPU a node's error is taken as. Measured per case-study node by
#: tests/bench/bench_cgroup_fairness.py (docs/benchmarks.md, "Emulated computers, measured"):
#: a cgroup capped at 1.0x or 1.1x of a node's measured need lost up to 34 % / 7.5 % of its
#: frames (the need itself moves between windows), at 1.25x none in any run; so a plan keeps
#: at least a quarter of each node's CPU free under ``--headroom auto`` (cap >= 1.25x need).
FAIR_SHARE = 0.25

#: CPU units within which a curve level counts as a setting's own CPU
_SAME_LEVEL = 1e-6


def states_errors(system: System) -> bool:
    """Does any setting or node of ``system`` state a measured error?"""
    return any(s.cpu_error is not None or s.cpu_error_share is not None for n in system.nodes for s in n.settings) \
        or any(n.cpu_error_between is not None for n in system.nodes)


def choice_error(node: Node, choice: Choice) -> float:
    """CPU units ``choice`` (one of ``node``'s solver choices) may need beyond its ``cpu``:
    the rule of the module docstring, at least :data:`FAIR_SHARE` x its CPU."""
    floor = FAIR_SHARE * max(choice.cpu, 0.0)
    if node.driven:
        s = node.settings[choice.setting] if choice.setting is not None else None
        share = s.cpu_error_share if s is not None and s.cpu_error_share is not None else 0.0
        return max(share * max(choice.cpu, 0.0), floor)
    if node.curve is None:
        s = _setting_of(node, choice)
        stated = s.cpu_error if s is not None and s.cpu_error is not None else 0.0
        return max(stated, floor)
    return max(curve_error(node, choice.cpu), floor)


def curve_error(node: Node, cpu: float) -> float:
    """A curve node's stated error at CPU level ``cpu`` (no floor): its settings' errors,
    interpolated by CPU, plus ``cpu_error_between`` off their CPU levels; 0 without any."""
    points = sorted((s.cpu, s.cpu_error) for s in node.settings if s.cpu_error is not None)
    between = node.cpu_error_between or 0.0
    if not points:
        return between
    for c, e in points:
        if abs(c - cpu) <= _SAME_LEVEL:
            return e
    if cpu <= points[0][0]:
        return points[0][1] + between
    for (c0, e0), (c1, e1) in zip(points, points[1:], strict=False):
        if cpu <= c1:
            return e0 + (e1 - e0) * (cpu - c0) / (c1 - c0) + between
    return points[-1][1] + between


def _setting_of(node: Node, choice: Choice) -> Setting | None:
    """The discrete setting a choice of ``node`` is (by CPU, performance and value)."""
    for s in node.settings:
        if math.isclose(s.cpu, choice.cpu, rel_tol=1e-9, abs_tol=1e-9) \
                and math.isclose(s.performance, choice.performance, rel_tol=1e-9, abs_tol=1e-9) \
                and (s.value == choice.value or (s.value is not None and choice.value is not None
                                                 and math.isclose(s.value, choice.value, rel_tol=1e-9, abs_tol=1e-9))):
            return s
    return None
