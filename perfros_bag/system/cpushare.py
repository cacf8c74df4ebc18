"""How a capped computer shares its CPU among its nodes: the one model that the kept-rate
prediction (validation), the latency model and ``watch`` use.

A computer of capacity C is, on this machine, a cgroup whose CFS bandwidth quota is C. Inside
it the Linux scheduler (CFS) is fair per *thread*, not per process: every runnable thread gets
an equal slice, and a thread that asks for less than its slice keeps what it asks for while the
rest is shared among the others (max-min fairness, "water-filling"). A node with k busy threads
therefore gets up to k slices. Its share is

    share_i = min(need_i, k_i * L)

where the level L is the largest value with Σ_i min(need_i, k_i * L) <= C. When the needs fit
(Σ need <= C) every node gets its need. A node can never use more than its threads can run:
``max_units`` (k_i cores' worth of units) bounds its need first.

Two time scales, one rule. A *burst* (a message reaches idle nodes at once, and they run
until each has done its work: the latency model's service time) runs a node's busy threads
side by side, so k threads are k slices. A *sustained* overload (the computer throttled period
after period: the kept rates of validate and ``watch``) gives each node **one slice**, whatever
its threads (``sustained=True``): a worker pool's threads wait on each other at every barrier
(OpenCV's parallel HOG), so while one is descheduled the others idle. Measured in RQ3 on a
15-unit robot (camera 10 Hz, people_detect with 2.0 busy threads beside smoothing with 1.1,
eight runs of three configurations, 2026-11-27): one slice per node is off by 1.1 units per node
on average, threads as slices by 1.9 (people got 5.1-9.1 units, smoothing 4.9-8.1: the runs
scatter, the one-slice rule sits in their middle). ``max_units`` still bounds what a node runs.

This replaces the proportional rule (share = C * need / Σ need), which under-predicts light nodes:
CFS gives a node asking for little all it asks for.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Demand:
    """One node's claim on its computer's CPU, in the system's CPU units."""

    name: str
    need: float  # what it would use unhindered
    threads: float = 1.0  # busy threads: its weight in a burst's fair share (>= 1)
    max_units: float = math.inf  # the most its threads can run (threads x units per core)


def _slices(d: Demand, sustained: bool) -> float:
    """A demand's weight in the share: its busy threads in a burst, one when sustained."""
    return 1.0 if sustained else max(1.0, d.threads)


def fair_shares(capacity: float, demands: Sequence[Demand], *, sustained: bool = False) -> dict[str, float]:
    """Each demand's CPU share on a computer of ``capacity`` (the module's rule): threads
    as slices, or one slice per node when ``sustained``."""
    want = {d.name: max(0.0, min(d.need, d.max_units)) for d in demands}
    if len(want) != len(demands):
        raise ValueError("fair_shares: demand names must be unique")
    if sum(want.values()) <= capacity:
        return want
    weight = {d.name: _slices(d, sustained) for d in demands}
    # satisfy the demands in the order of their need per slice; the rest share the level
    order = sorted(want, key=lambda n: want[n] / weight[n])
    left, w_left = max(0.0, capacity), sum(weight.values())
    shares: dict[str, float] = {}
    for i, name in enumerate(order):
        level = left / w_left if w_left > 0 else 0.0
        if want[name] <= weight[name] * level:
            shares[name] = want[name]
            left -= want[name]
            w_left -= weight[name]
            continue
        for rest in order[i:]:
            shares[rest] = weight[rest] * level
        break
    return shares


def share_level(capacity: float, demands: Sequence[Demand], *, sustained: bool = False) -> float:
    """The per-slice level L of the rule (``inf`` when every need fits)."""
    shares = fair_shares(capacity, demands, sustained=sustained)
    capped = [shares[d.name] / _slices(d, sustained) for d in demands
              if shares[d.name] < max(0.0, min(d.need, d.max_units))]
    return max(capped) if capped else math.inf
