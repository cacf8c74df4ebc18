"""The latency model: every chain's delay, hop by hop, predicted from what the model holds.

A chain (system.yaml ``chains``) is topics ``t0 -> t1 -> ... -> tk``; hop ``i`` is the node
that publishes ``t_i`` driven by ``t_{i-1}`` (its ``input``, so it copies the stamp). A hop's
delay, for a node ``n`` on computer ``c`` at its planned choice, receiving ``lam`` messages
per second from its input's publisher ``m`` on computer ``c_m`` (docs/solvers.md, "Latency"):

* **service** ``S = scale_n x`` the wall time of one message (:func:`service_time`): every
  node of the computer driven by the same input gets the message at the same moment, so
  they run together, each at its fair share of what is left beside the others at their
  planned CPU, until one finishes and the rest share what it leaves. Alone, that is
  ``w / v`` seconds: ``w = cpu_n / lam`` CPU units x seconds per
  message (a driven node's CPU is ``cpu + cpu_per_hz x lam``, so ``w`` carries it), ``v`` the
  CPU units ``n`` runs at while it is busy: its share of its computer when it asks for all its
  threads can run (``threads x units_per_core``; system.yaml ``threads``, 1 by default) and
  the others ask for their planned CPU, each weighted by its threads
  (:func:`perfros_bag.system.cpushare.fair_shares`, the one model of how a capped computer
  shares its CPU). ``scale_n`` (fitted; 1 by default) turns CPU time into wall time. On
  computers that are CFS-capped cgroups (``cfs_period_ms`` > 0, as ``deploy``'s are) a node
  that finds its cgroup idle ends one period sooner (:func:`burst_time`).
* **wait** in its queue. The hop's input arrives periodically (every ``T = 1 / lam``: a
  chain starts at a timer-driven source, and each hop passes its input's period on), so the
  queue is D/D/1, not M/D/1: at utilisation ``rho = lam x w / v <= 1`` a message finds the node
  idle (at exactly 1, just freed: a node that gets exactly its planned CPU, as on a Problem 2
  server sized to its load, within rounding) and waits 0. Above 1 the node is always busy and
  ROS's drop-oldest queue of ``queue_size`` messages is full whenever it takes one, and so are the socket buffers ahead
  of it, which hold ``backlog_msgs`` more (first in, first out: the throttled node's own
  receive thread drains them; measured ~2 of 230 kB frames). The node takes the oldest of the
  ``H = queue_size + backlog_msgs`` newest arrivals, so a delivered message waits
  ``(H - 1 + u) x T`` with ``u`` uniform on [0, 1) (the running message ends at any point of
  an input period): the quantile ``q`` is ``(H - 1 + q) x T``, never more than ``H x S``
  (``T <= S`` there).
* **transfer** of the input's message (``B`` kB: its bandwidth over its frequency at ``m``'s
  choice) across every link and shared medium of ``System.route(c_m, c)``: the slowest
  element's ``B / (efficiency x bandwidth)`` (a message streams across the route), less
  ``link_burst_ms`` (at least 0) on an element whose load is below its bandwidth (a shaper's
  bucket, full again when the message comes: deploy's ``tbf`` lets 10 ms pass at once), plus at each
  element a wait behind the *other* traffic: their streams' phases are unrelated to the
  hop's, so it is M/D/1, mean ``k x u x t / (2 (1 - u))`` (``k`` = ``queue_factor``) for
  its transfer time ``t``, 0 with probability ``1 - u`` and else exponential, at the
  utilisation of that traffic (its planned load less the hop's own stream, which is
  periodic and does not queue behind itself; at most 0.99).
* **overhead**: ``overhead_ms`` (fitted) per hop.

p50 = overhead + transfer + wait_p50 + S; p95 = overhead + transfer_p95 + wait_p95 +
``p95_ratio_n`` x S. A chain's p50/p95 is the sum of its hops' (for p95 an upper bound when the
hops' delays are positively related, as on a shared computer).

Every term grows with the load of the node's computer and of the links on its route, so the
prediction is monotone in what else a plan puts there: the exact solver's budget cuts rely on
it (solver/exact.py). solver/check.py keeps its own, independent copy of this rule.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import PerfrosWarning
from perfros_bag.system.cpushare import Demand, fair_shares
from perfros_bag.system.types import Budget, Chain, Choice, LatencyParams, System, TopicRate

if TYPE_CHECKING:
    from perfros_bag.system.plan import Plan

#: a link or medium's utilisation is taken as at most this (a forced plan may overload one)
MAX_UTILISATION = 0.99
#: a node's utilisation up to this is not over 1: a node that gets exactly its planned CPU (a
#: Problem 2 server sized to its load) computes to 1 within rounding, either side of it
SATURATED = 1 + 1e-9


@dataclass(frozen=True)
class Hop:
    """One hop of a chain: ``node`` publishes ``dst`` driven by ``src``."""

    src: str
    node: str
    dst: str


@dataclass(frozen=True)
class HopPrediction:
    src: str
    node: str
    dst: str
    computer: str
    p50_ms: float
    p95_ms: float
    service_ms: float
    wait_ms: float  # p50 of the queue's wait
    transfer_ms: float
    utilisation: float
    wait_p95_ms: float = 0.0
    transfer_p95_ms: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {"from": self.src, "node": self.node, "to": self.dst, "computer": self.computer,
                "predicted_ms": {"p50": _ms(self.p50_ms), "p95": _ms(self.p95_ms)},
                "service_ms": _ms(self.service_ms), "wait_ms": _ms(self.wait_ms),
                "transfer_ms": _ms(self.transfer_ms), "utilisation": round(self.utilisation, 6),
                "wait_p95_ms": _ms(self.wait_p95_ms), "transfer_p95_ms": _ms(self.transfer_p95_ms)}


@dataclass(frozen=True)
class ChainPrediction:
    """A chain's predicted latency; ``why`` (and no numbers) when it cannot be predicted."""

    name: str
    topics: tuple[str, ...]
    budget: Budget | None
    p50_ms: float | None = None
    p95_ms: float | None = None
    hops: tuple[HopPrediction, ...] = ()
    why: str | None = None

    def over_budget(self, tol: float = 1e-6) -> list[tuple[str, float, float]]:
        """(quantile, predicted ms, budget ms) for each bound the prediction breaks (a chain
        that cannot be predicted breaks every bound it has)."""
        if self.budget is None:
            return []
        got = {"p50": math.inf if self.p50_ms is None else self.p50_ms,
               "p95": math.inf if self.p95_ms is None else self.p95_ms}
        return [(q, got[q], b) for q, b in self.budget.items() if got[q] > b * (1 + tol) + tol]

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "name": self.name, "topics": list(self.topics),
            "predicted_ms": None if self.p50_ms is None else {"p50": _ms(self.p50_ms), "p95": _ms(self.p95_ms)},
            "budget_ms": None if self.budget is None else self.budget.to_dict(),
            "hops": [h.to_dict() for h in self.hops],
        }
        if self.why is not None:
            out["unpredicted"] = self.why
        return out


def _ms(v: float | None) -> float | None:
    return None if v is None or not math.isfinite(v) else round(v, 6)


def chain_hops(system: System, chain: Chain) -> list[Hop] | str:
    """The hops of ``chain``, or why they cannot be followed (a topic no node publishes from
    the topic before it: that node stamps afresh, or nothing joins them)."""
    hops: list[Hop] = []
    for a, b in zip(chain.topics, chain.topics[1:], strict=False):
        pubs = system.publishers.get(b, ())
        driven = [n for n in pubs if system.node[n].input == a]
        if not driven:
            if pubs:
                who = ", ".join(map(repr, pubs))
                return (f"hop {a} -> {b}: {b} is published by {who}, not driven by {a} "
                        f"(system.yaml input:), so its messages are stamped afresh")
            return f"hop {a} -> {b}: no node publishes {b}"
        hops.append(Hop(a, driven[0], b))
    return hops


def _topic_bytes_kB(system: System, node: str, choice: Choice, topic: str) -> float:
    """kB per message of ``topic`` at its publisher's choice (0 when it has no rate)."""
    hz = system.topic_hz(choice, topic)
    rate = choice.topics.get(topic)
    bw = rate.bandwidth_kBps if rate is not None and rate.bandwidth_kBps is not None else None
    if bw is None and choice.bandwidth_kBps is not None:
        bw = choice.bandwidth_kBps / max(1, len(system.node[node].topics))
    if not hz or bw is None:
        return 0.0
    return bw / hz


def wait_quantile(mean_wait: float, rho: float, q: float) -> float:
    """The ``q`` quantile of an M/D/1 queue's wait with mean ``mean_wait`` at utilisation
    ``rho`` (a link's traffic of others): 0 with probability ``1 - rho``, else exponential
    with mean ``mean_wait / rho``."""
    if rho <= 0 or mean_wait <= 0 or rho <= 1 - q:
        return 0.0
    return mean_wait / rho * math.log(rho / (1 - q))


def queue_wait(service_s: float, rho: float, params: LatencyParams, q: float, period_s: float) -> float:
    """Seconds a message waits for the node (quantile ``q``) when its input arrives every
    ``period_s``: 0 up to ``rho`` 1 (D/D/1: a periodic message finds the node idle, or just
    freed at exactly 1, as on a Problem 2 server sized to its load; :data:`SATURATED`); above
    ROS's drop-oldest queue and the ``backlog_msgs`` ahead of it are full when the node
    takes its oldest message, so it waited ``queue_size + backlog_msgs - 1`` periods and the
    rest of one (uniform: quantile ``q``); never more than ``(queue_size + backlog_msgs) x
    service_s``."""
    if rho <= SATURATED:
        return 0.0
    held = params.queue_size + params.backlog_msgs
    return min((held - 1 + q) * period_s, held * service_s)


def threads_of(system: System, node: str, choice: Choice) -> float:
    """Busy threads of ``node`` at its choice (system.yaml ``threads``, per setting or node; 1)."""
    n = system.node.get(node)
    return 1.0 if n is None else max(1.0, n.threads_at(choice.value))


def released_together(system: System, node: str, computer: str, placement: Mapping[str, str],
                      choice: Mapping[str, Choice]) -> list[str]:
    """The nodes of ``computer`` driven by ``node``'s input (``node`` among them): each
    message reaches them at the same moment, so they run at the same time."""
    topic = system.node[node].input
    return [n for n, c in placement.items()
            if c == computer and n in choice and n in system.node and system.node[n].input == topic]


def service_time(system: System, node: str, computer: str, placement: Mapping[str, str],
                 choice: Mapping[str, Choice], capacity: float, lam: float) -> float:
    """Seconds (wall, before ``service_scale``) ``node`` takes for one message on
    ``computer``: it and the nodes released with it (:func:`released_together`) each start
    their ``cpu / lam`` units x seconds at once and share the computer as CFS does while they
    run (:func:`perfros_bag.system.cpushare.fair_shares`: each asks for all its threads can
    run, weighted by its threads), beside the other nodes at their planned CPU; when one
    finishes the rest share what it leaves. Inf when it gets no CPU."""
    upc = system.latency.units_per_core
    together = released_together(system, node, computer, placement, choice)
    left = {n: choice[n].cpu / lam for n in together}
    rest = [Demand(n, choice[n].cpu, threads_of(system, n, choice[n]))
            for n, c in placement.items() if c == computer and n in choice and n not in left]
    t = 0.0
    while left.get(node, 0.0) > 0:
        k = {n: threads_of(system, n, choice[n]) for n in left}
        shares = fair_shares(capacity, rest + [Demand(n, math.inf, k[n], k[n] * upc) for n in left])
        running = {n: shares[n] for n in left if shares[n] > 0}
        if node not in running:
            return math.inf
        first = min(running, key=lambda n: left[n] / running[n])
        dt = left[first] / running[first]
        t += dt
        for n, v in running.items():
            left[n] -= v * dt
        left = {n: w for n, w in left.items() if n != first and w > 1e-12}
    return t


def burst_time(busy: float, alone: float, rho: float, params: LatencyParams) -> float:
    """Seconds a message's burst takes on a CFS-capped computer (``params.cfs_period_ms`` >
    0), from the fluid ``busy`` (:func:`service_time`): a node that finds its cgroup idle
    (``rho`` <= 1) runs its period's quota at once, at its threads' speed, and its last
    quota ends part-way into a period, so the burst ends on average one period before the
    fluid time (measured on this machine, 15-unit cgroup, 10 ms period: 13 ms of CPU per
    burst took 75.5 ms against 86.7 fluid, 6 ms took 28.5 against 40); never below
    ``alone``, its time at its threads' speed. A saturated node (``rho`` > 1) finds no quota
    left: ``busy``. Non-decreasing in ``busy`` and ``rho``, so the prediction stays monotone
    in the load beside the node."""
    period = params.cfs_period_ms / 1000.0
    if period <= 0 or rho > SATURATED or busy <= alone:
        return busy
    return max(busy - period, alone)


def _link_terms(system: System, route: Sequence[int], link_loads: Sequence[float], size_kB: float,
                own_kBps: float, params: LatencyParams) -> tuple[float, float, float]:
    """(base seconds, wait p50, wait p95) of a message of ``size_kB`` across ``route``; the
    wait at each element is for the traffic of others (its load less ``own_kBps``, the
    hop's own periodic stream, which does not queue behind itself)."""
    elements: list[tuple[float, float]] = []  # (bandwidth, load)
    media: set[str] = set()
    for li in route:
        link = system.links[li]
        elements.append((link.bandwidth_kBps, link_loads[li]))
        if link.medium is not None:
            media.add(link.medium)
    for m in sorted(media):
        elements.append((system.medium[m].bandwidth_kBps, system.medium_load(link_loads, m)))
    base = w50 = w95 = 0.0
    for bw, load in elements:
        if bw <= 0:
            return math.inf, math.inf, math.inf
        t = size_kB / (params.link_efficiency * bw)
        # below its rate its bucket refilled since the last message: the first part crosses at once
        base = max(base, max(0.0, t - params.link_burst_ms / 1000.0) if load < bw else t)
        u = min(max(0.0, load - own_kBps) / bw, MAX_UTILISATION)
        mean = params.queue_factor * u * t / (2 * (1 - u))
        w50 += wait_quantile(mean, u, 0.5)
        w95 += wait_quantile(mean, u, 0.95)
    return base, w50, w95


def predict_hop(system: System, hop: Hop, placement: Mapping[str, str], choice: Mapping[str, Choice],
                capacities: Mapping[str, float], link_loads: Sequence[float]) -> HopPrediction | str:
    """One hop's prediction (the module's rule), or why it has none."""
    params = system.latency
    node = system.node[hop.node]
    ch = choice[hop.node]
    comp = placement[hop.node]
    parent = system.publishers[hop.src][0]
    lam = ch.input_hz if ch.input_hz is not None else system.topic_hz(choice[parent], hop.src)
    if not lam or lam <= 0:
        return f"hop {hop.src} -> {hop.dst}: {node.name!r} has no measured input rate"
    cap = capacities.get(comp, math.inf)
    if not math.isfinite(cap):  # a server to be sized: its load
        cap = sum(choice[n].cpu for n, c in placement.items() if c == comp and n in choice)
    busy = service_time(system, hop.node, comp, placement, choice, cap, lam)
    if not math.isfinite(busy):
        return f"hop {hop.src} -> {hop.dst}: {node.name!r} gets no CPU on {comp}"
    rho = lam * busy
    alone = ch.cpu / lam / (threads_of(system, hop.node, ch) * params.units_per_core)
    service = params.service_scale.get(hop.node, 1.0) * burst_time(busy, alone, rho, params)
    wait50, wait95 = queue_wait(service, rho, params, 0.5, 1 / lam), queue_wait(service, rho, params, 0.95, 1 / lam)
    transfer50 = transfer95 = 0.0
    src_comp = placement[parent]
    if src_comp != comp:
        route = system.route(src_comp, comp)
        if route is None:
            return f"hop {hop.src} -> {hop.dst}: no network path from {src_comp} to {comp}"
        size = _topic_bytes_kB(system, parent, choice[parent], hop.src)
        own = size * (system.topic_hz(choice[parent], hop.src) or 0.0)
        base, n50, n95 = _link_terms(system, route, link_loads, size, own, params)
        transfer50, transfer95 = base + n50, base + n95
    ratio = params.node_p95_ratio.get(hop.node, params.p95_ratio)
    over = params.overhead_ms / 1000.0
    p50 = over + transfer50 + wait50 + service
    p95 = over + transfer95 + wait95 + ratio * service
    return HopPrediction(hop.src, hop.node, hop.dst, comp, 1000 * p50, 1000 * p95, 1000 * service,
                         1000 * wait50, 1000 * transfer50, rho, 1000 * wait95, 1000 * transfer95)


def predict_chain(system: System, chain: Chain, placement: Mapping[str, str], choice: Mapping[str, Choice],
                  capacities: Mapping[str, float], link_loads: Sequence[float] | None = None) -> ChainPrediction:
    """``chain`` predicted for a placement and choices (``capacities``: each computer's CPU;
    ``link_loads``: :meth:`System.link_loads`, computed when not given)."""
    hops = chain_hops(system, chain)
    if isinstance(hops, str):
        return ChainPrediction(chain.name, chain.topics, chain.budget_ms, why=hops)
    if any(h.node not in placement or system.publishers[h.src][0] not in placement for h in hops):
        return ChainPrediction(chain.name, chain.topics, chain.budget_ms, why="a node of it is not placed")
    loads = system.link_loads(placement, choice) if link_loads is None else link_loads
    out: list[HopPrediction] = []
    for hop in hops:
        got = predict_hop(system, hop, placement, choice, capacities, loads)
        if isinstance(got, str):
            return ChainPrediction(chain.name, chain.topics, chain.budget_ms, why=got)
        out.append(got)
    return ChainPrediction(chain.name, chain.topics, chain.budget_ms, sum(h.p50_ms for h in out),
                           sum(h.p95_ms for h in out), tuple(out))


def plan_predictions(system: System, plan: Plan, *, warn: bool = True) -> list[ChainPrediction]:
    """Every chain predicted for a plan as it states itself (each node's computer, CPU, input
    rate and topics; each computer's capacity, a sized server's too; the links' loads): the
    rule :func:`predict_chains` applies to a solver's answer, on the plan's own numbers, so a
    plan restated after the solve (headroom given back) is predicted as it will run."""
    if not system.chains or not plan.nodes:
        return []
    placement = {n: pn.computer for n, pn in plan.nodes.items()}
    choice = {n: Choice(0, pn.cpu, pn.performance, pn.value, None,
                        sum(r.bandwidth_kBps or 0.0 for r in pn.topics.values()),
                        {t: TopicRate(r.frequency_hz, r.bandwidth_kBps) for t, r in pn.topics.items()},
                        input_hz=pn.input_hz)
              for n, pn in plan.nodes.items()}
    caps = {name: c.capacity if c.capacity is not None else c.cpu for name, c in plan.computers.items()}
    same = len(plan.links) == len(system.links) and all(
        tuple(pl.between) == tuple(link.between) for pl, link in zip(plan.links, system.links, strict=True))
    loads = [pl.load_kBps for pl in plan.links] if same else system.link_loads(placement, choice)
    out = [predict_chain(system, c, placement, choice, caps, loads) for c in system.chains]
    if warn:
        for p in out:
            if p.why is not None:
                warnings.warn(f"{system.source or 'system'}: chain {p.name!r}: "
                              f"its latency cannot be predicted: {p.why}",
                              PerfrosWarning, stacklevel=2)
    return out


def budget_violation(system: System, placement: Mapping[str, str], choice: Mapping[str, Choice],
                     capacities: Mapping[str, float]) -> str | None:
    """Why a (whole) placement breaks a chain's budget (predicted over it), or None."""
    budgeted = [c for c in system.chains if c.budget_ms is not None]
    if not budgeted:
        return None
    loads = system.link_loads(placement, choice)
    for chain in budgeted:
        p = predict_chain(system, chain, placement, choice, capacities, loads)
        over = p.over_budget()
        if over:
            q, got, limit = over[0]
            return f"chain {chain.name!r}: predicted {q} {got:.4g} ms > budget {limit:g} ms"
    return None


def hop_floor(system: System, node: str, choice: Choice, capacity: float) -> tuple[float, float] | None:
    """A lower bound on the (p50, p95) ms of ``node``'s hop at ``choice`` on a computer of
    ``capacity``, whatever else the plan puts there: the node at the most it can run (its
    threads' cores, at most the capacity), its wait at that speed, no transfer. None without
    an input rate."""
    params = system.latency
    lam = choice.input_hz
    v = min(threads_of(system, node, choice) * params.units_per_core, capacity)
    if not lam or lam <= 0 or v <= 0:
        return None
    w = choice.cpu / lam
    rho = lam * w / v
    alone = w / (threads_of(system, node, choice) * params.units_per_core)
    s = params.service_scale.get(node, 1.0) * burst_time(w / v, alone, rho, params)
    ratio = params.node_p95_ratio.get(node, params.p95_ratio)
    over = params.overhead_ms / 1000.0
    return (1000 * (over + s + queue_wait(s, rho, params, 0.5, 1 / lam)),
            1000 * (over + ratio * s + queue_wait(s, rho, params, 0.95, 1 / lam)))


def fastest_bound(system: System, chain: Chain, choices: Mapping[str, Sequence[Choice]]) -> tuple[float, float] | None:
    """A lower bound on ``chain``'s predicted (p50, p95) over every plan: each hop at its
    fastest choice, alone on the largest computer it may use, beside its input's publisher
    (:func:`hop_floor`). None when the chain cannot be followed."""
    hops = chain_hops(system, chain)
    if isinstance(hops, str):
        return None
    p50 = p95 = 0.0
    for hop in hops:
        caps = [c.capacity if c.capacity is not None else (c.max_capacity or math.inf)
                for c in system.computers if c.name in system.allowed(hop.node)]
        cap = max(caps) if caps else 0.0
        floors = [f for ch in choices.get(hop.node, ()) if (f := hop_floor(system, hop.node, ch, cap)) is not None]
        p50 += min((f[0] for f in floors), default=math.inf)
        p95 += min((f[1] for f in floors), default=math.inf)
    return p50, p95


def budget_text(budget: object) -> str:
    """A ``budget_ms`` as text (``p50 100 ms, p95 150 ms``); ``-`` without one."""
    if not isinstance(budget, Mapping) or not budget:
        return "-"
    return ", ".join(f"{q} {budget[q]:g} ms" for q in ("p50", "p95") if isinstance(budget.get(q), int | float))
