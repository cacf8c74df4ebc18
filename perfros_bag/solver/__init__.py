"""Solvers for the paper's two problems (section II), one entry point: :func:`solve`.

- Problem 1 (eq 1): choose a setting and a computer for every node to maximise
  Σ w·P under eq 3-9.
- Problem 2 (eq 2): settings are fixed (``settings``, default each node's maximum-CPU
  choice); choose a computer per node to minimise the total server capacity (robots keep
  their capacity; a server's size is its load, bounded by ``max_capacity`` when set).

Every solver receives the same candidates from :func:`fixed_choices` and has the
signature ``(system, problem, choices) -> Plan`` (the exact solver also takes
``time_limit``):

- ``greedy``      :func:`perfros_bag.solver.greedy.solve_greedy` (the paper's Algorithms 1-3)
- ``greedy+``     :func:`perfros_bag.solver.local.solve_greedy_plus` (greedy + local search)
  (with driven nodes both run per rate class of each publisher:
  :func:`perfros_bag.solver.flow.solve_heuristic`)
- ``exact``       ``perfros_bag.solver.exact.solve_exact(system, problem, choices, *, time_limit=None)``;
  on Problem 1 above :data:`DECOMPOSE_COLUMNS` columns :func:`solve` uses
  :func:`perfros_bag.solver.decompose.solve_decomposed` (column generation over the
  fleet's structure, a plan and a proven bound) when the instance qualifies (CPU on a
  grid; links and media that can overflow carried as coupling rows; no driven nodes:
  :func:`perfros_bag.solver.decompose.decomposable`); otherwise, above
  :data:`START_COLUMNS`, it first runs greedy+ (along the data flow when there is one,
  :mod:`perfros_bag.solver.flow`) for :data:`START_SHARE` of ``time_limit`` and passes
  its plan as the MIP start
- ``bruteforce``  :func:`perfros_bag.solver.bruteforce.solve_bruteforce` (tiny instances)

``settings`` (Problem 2) maps node -> **CPU level** (units of the system's CPU scale).
:func:`settings_from_values` converts node -> parameter value to CPU levels, and
:func:`settings_from_plan` takes them from a plan.json.

This file is the public entry only; the modules, each importing only those below it:
``candidates`` (the choices and ``settings``), ``state`` -> ``greedy`` -> ``local`` ->
``flow`` (the heuristics), ``instance`` and ``milp`` (the pruned instance and the HiGHS
model the exact methods share) -> ``starts`` (MIP starts from the heuristics) -> ``exact``,
``decompose``; ``dispatch`` (:func:`solve`) above the methods, ``frontier`` above it;
``bruteforce`` and ``check`` stand alone (docs/architecture.md).
"""

from perfros_bag.solver.candidates import (
    MAX_CHOICES,
    DrivenLevel,
    check_resolution,
    choice_count,
    fixed_choices,
    lowest_settings,
    settings_from_plan,
    settings_from_values,
)
from perfros_bag.solver.dispatch import (
    AUTO,
    DECOMPOSE_COLUMNS,
    METHODS,
    START_COLUMNS,
    START_SHARE,
    check_headroom,
    exact_columns,
    inflate_choices,
    solve,
    with_headroom,
)
from perfros_bag.solver.instance import Progress

__all__ = ["AUTO", "DECOMPOSE_COLUMNS", "MAX_CHOICES", "METHODS", "START_COLUMNS", "START_SHARE", "DrivenLevel",
           "Progress", "check_headroom", "check_resolution", "choice_count", "exact_columns", "fixed_choices",
           "inflate_choices", "lowest_settings", "settings_from_plan", "settings_from_values", "solve",
           "with_headroom"]
