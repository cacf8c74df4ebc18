"""The rates a plan keeps when a computer cannot give its nodes the CPU they need (RQ3,
beyond the paper, which only says "overloaded"). The rule (docs/formats.md, "validate: kept
rates"):

- a node's need is its CPU at its current input rate (a driven node: the data-flow rule of
  :func:`perfros_bag.system.types.driven_rates` at its planned setting; any other node: its
  planned CPU), times its calibration (measured / planned CPU where the run showed more);
- a computer whose nodes need more than its capacity shares it as CFS does under a sustained
  overload (:func:`perfros_bag.system.cpushare.fair_shares`, ``sustained``): max-min fair, one
  slice per node, so a node that needs less than its slice keeps all it needs and the others
  share the rest (a node's busy threads, system.yaml ``threads``, do not widen its slice then:
  measured, see that module); its output rate scales by share / need;
- a node's lower output rate is the lower input rate of the nodes it drives: their need and
  their output fall too, all the way down the ``input`` chains;
- repeated to a fixed point (damped: each round moves the input rates half way to what the
  shares give), from the planned rates.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from perfros_bag.system.cpushare import Demand, fair_shares
from perfros_bag.system.plan import Plan
from perfros_bag.system.types import Setting, System, driven_rates

#: the fixed point: input rates that move less than this (relative) in a round
TOLERANCE = 1e-12
#: rounds at most (the damped map halves its error each round at least on a chain)
MAX_ROUNDS = 2000


@dataclass
class KeptNode:
    """One node of the plan under the shared CPU: what it needs, gets and keeps."""

    node: str
    computer: str
    cpu_planned: float
    cpu_need: float  # at the fixed point's input rate (calibrated)
    cpu_share: float  # what its computer gives it
    factor: float  # share / need: the fraction of its rate it keeps (1: not capped)
    f_planned: float | None  # its planned output rate (mean over its topics)
    f_predicted: float | None  # its predicted output rate (same topics)
    f_measured: float | None = None  # the run's (mean over its topics), when validated against one
    input: str | None = None  # a driven node's input topic
    input_hz_planned: float | None = None
    input_hz_predicted: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"node": self.node, "computer": self.computer, "cpu_planned": self.cpu_planned,
                "cpu_need": self.cpu_need, "cpu_share": self.cpu_share, "factor": self.factor,
                "f_planned": self.f_planned, "f_predicted": self.f_predicted, "f_measured": self.f_measured,
                "input": self.input, "input_hz_planned": self.input_hz_planned,
                "input_hz_predicted": self.input_hz_predicted}


@dataclass
class KeptComputer:
    computer: str
    capacity: float
    need: float  # Σ of its nodes' needs at the fixed point
    capped: bool  # need > capacity: its nodes share it

    def to_dict(self) -> dict[str, Any]:
        return {"computer": self.computer, "capacity": self.capacity, "need": self.need, "capped": self.capped}


@dataclass
class KeptRates:
    """The prediction: per node and computer, with how it was reached."""

    nodes: list[KeptNode]
    computers: list[KeptComputer]
    rounds: int
    converged: bool
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        return {"nodes": [n.to_dict() for n in self.nodes], "computers": [c.to_dict() for c in self.computers],
                "rounds": self.rounds, "converged": self.converged, "notes": self.notes}


def planned_settings(plan: Plan, system: System | None) -> tuple[dict[str, Setting], list[str]]:
    """Each driven node's setting (system.yaml ``input:``) the plan chose, by its value; a
    driven node whose value matches no setting is left out (a note says so)."""
    out: dict[str, Setting] = {}
    notes: list[str] = []
    if system is None:
        if any(pn.input is not None for pn in plan.nodes.values()):
            notes.append("no system: the driven nodes' CPU and rates do not follow their inputs in the kept-rate "
                         "prediction (each keeps its computer's share only)")
        return out, notes
    for name, pn in plan.nodes.items():
        node = system.node.get(name)
        if node is None or not node.driven or pn.input_hz is None:
            continue
        j = node.setting_index(pn.value)
        s = None if j is None else node.settings[j]
        if s is None and len(node.settings) == 1:
            s = node.settings[0]
        if s is None:
            notes.append(f"node {name!r}: its planned value {pn.value} is none of its settings in the system: "
                         "its CPU does not follow its input in the prediction")
            continue
        out[name] = s
    return out, notes


def overloaded_capacities(plan: Plan, system: System | None) -> dict[str, float]:
    """The capacity each planned computer has: the system's (the robot it runs on) when it
    gives one, else the plan's."""
    out: dict[str, float] = {}
    for name, pc in plan.computers.items():
        cap = system.computer[name].capacity if system is not None and name in system.computer else None
        cap = pc.capacity if cap is None else cap
        if cap is not None:
            out[name] = cap
    return out


def predict_kept(plan: Plan, system: System | None, capacities: Mapping[str, float],
                 calibration: Mapping[str, float] | None = None) -> KeptRates:
    """The rates each node of ``plan`` keeps on computers of ``capacities`` (the rule of the
    module's docstring). ``calibration``: per node, measured / planned CPU (default 1)."""
    calibration = calibration or {}
    settings, notes = planned_settings(plan, system)
    parent = {n: system.flow_parent[n] for n in settings} if system is not None else {}
    parent = {n: p for n, p in parent.items() if p in plan.nodes}
    inputs = {n: float(plan.nodes[n].input_hz or 0.0) for n in settings}

    def topic_rates(name: str) -> dict[str, float]:
        return {t: r.frequency_hz for t, r in plan.nodes[name].topics.items() if r.frequency_hz is not None}

    def evaluate(fin: Mapping[str, float]
                 ) -> tuple[dict[str, float], dict[str, float], dict[str, float], dict[str, float]]:
        """need, computer factor per node, output rate per node (planned: per the rule at fin),
        and the input rates the outputs give."""
        need: dict[str, float] = {}
        out_at: dict[str, float | None] = {}
        for name, pn in plan.nodes.items():
            if name in settings:
                cpu, f_out, _ = driven_rates(settings[name], fin[name])
                need[name], out_at[name] = cpu, f_out
            else:
                need[name], out_at[name] = pn.cpu, None
            need[name] *= calibration.get(name, 1.0)
        load: dict[str, float] = {}
        demands: dict[str, list[Demand]] = {}
        for name, pn in plan.nodes.items():
            load[pn.computer] = load.get(pn.computer, 0.0) + need[name]
            demands.setdefault(pn.computer, []).append(Demand(name, need[name]))  # one slice each: sustained
        factor = {}
        for comp, ds in demands.items():
            cap = capacities.get(comp)
            shares = {d.name: d.need for d in ds} if cap is None else fair_shares(cap, ds, sustained=True)
            for d in ds:
                factor[d.name] = 1.0 if d.need <= 0 else min(1.0, shares[d.name] / d.need)
        new_in: dict[str, float] = {}
        for name, p in parent.items():
            topic = system.node[name].input if system is not None else None
            base = out_at[p] if out_at[p] is not None else topic_rates(p).get(topic or "", 0.0)
            new_in[name] = (base or 0.0) * factor[p]
        return need, factor, load, new_in

    rounds, converged = 0, not parent
    fin = dict(inputs)
    while rounds < MAX_ROUNDS and parent:
        rounds += 1
        _, _, _, target = evaluate(fin)
        step = {n: 0.5 * (fin[n] + target.get(n, fin[n])) for n in fin}
        moved = max((abs(step[n] - fin[n]) / max(1.0, abs(fin[n])) for n in fin), default=0.0)
        fin = step
        if moved <= TOLERANCE:
            converged = True
            break
    if not converged:
        notes.append(f"the kept rates did not settle in {MAX_ROUNDS} rounds: the last round's are shown")
    need, factor, load, _ = evaluate(fin)
    nodes: list[KeptNode] = []
    for name, pn in plan.nodes.items():
        planned = topic_rates(name)
        f_plan = sum(planned.values()) / len(planned) if planned else None
        if name in settings:
            f_pred: float | None = driven_rates(settings[name], fin[name])[1] * factor[name]
        else:
            f_pred = None if f_plan is None else f_plan * factor[name]
        nodes.append(KeptNode(name, pn.computer, pn.cpu, need[name], need[name] * factor[name], factor[name],
                              f_plan, f_pred, input=pn.input, input_hz_planned=pn.input_hz,
                              input_hz_predicted=fin.get(name)))
    computers = [KeptComputer(c, capacities[c], load.get(c, 0.0), load.get(c, 0.0) > capacities[c])
                 for c in plan.computers if c in capacities]
    for n in nodes:
        if n.f_predicted is not None and not math.isfinite(n.f_predicted):
            n.f_predicted = None
    return KeptRates(nodes, computers, rounds, converged, notes)
