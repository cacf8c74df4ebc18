"""An independent feasibility checker of a plan against its system (eq 1-9).

It recomputes everything from the system and the plan's per-node answer (computer, CPU,
performance), sharing no code with the solvers or with :func:`perfros_bag.system.rules.build_plan`:
the model's own definitions (a setting's bandwidth, the route between two computers) are
the only things it takes from :mod:`perfros_bag.system.types`.
"""

from __future__ import annotations

import math
from collections import defaultdict

from perfros_bag.system.plan import Plan
from perfros_bag.system.types import Choice, Node, System


def _close(a: float, b: float, tol: float) -> bool:
    return abs(a - b) <= tol * max(1.0, abs(a), abs(b))


def _over(load: float, cap: float, tol: float) -> bool:
    return load > cap + tol * max(1.0, abs(cap))


def _node_choice(node: Node, cpu: float, performance: float, tol: float, value: float | None = None) -> Choice | None:
    """The node's setting the plan claims (matched on CPU and performance; among equals, the
    one with the plan's ``value``), or None."""
    if node.curve is None:
        match = [(i, s) for i, s in enumerate(node.settings)
                 if _close(s.cpu, cpu, tol) and _close(s.performance, performance, tol)]
        match.sort(key=lambda m: not (value is not None and m[1].value is not None and _close(m[1].value, value, tol)))
        for i, s in match[:1]:
            return Choice(i, s.cpu, s.performance, s.value, s.frequency_hz, s.bandwidth_kBps, s.topics)
    else:
        lo, hi = node.curve.domain
        if lo - tol * max(1.0, abs(lo)) <= cpu <= hi + tol * max(1.0, abs(hi)):
            if _close(node.curve(min(max(cpu, lo), hi)), performance, tol):
                return node.choice_at(0, min(max(cpu, lo), hi))
    return None


def _driven_choice(node: Node, input_hz: float, cpu: float, performance: float, tol: float,
                   value: float | None = None, copy_per_hz: float = 0.0) -> Choice | None:
    """A driven node's setting the plan claims at input rate ``input_hz``: its CPU is
    ``cpu + cpu_per_hz·F_in``, its output ``min(out_per_in·F_in, max_frequency_hz)`` (``step:
    period``: one per k messages of ``out_per_in·F_in``, k the fewest with k x cap >= it), its
    bandwidth ``bytes_per_msg`` per output message (docs/formats.md; this checker's own
    copy of the rule). Two settings with the same CPU and performance (their outputs may
    differ) are told apart by the plan's ``value``. A standalone node's CPU carries
    ``copy_per_hz`` more per input message (:func:`_copy_per_hz`)."""
    def named(j: int) -> bool:
        own = node.settings[j].value
        return value is not None and own is not None and _close(float(own), float(value), tol)

    order = sorted(range(len(node.settings)), key=lambda j: not named(j))
    for j in order:
        s = node.settings[j]
        need = s.cpu + ((s.cpu_per_hz or 0.0) + copy_per_hz) * input_hz
        if not (_close(need, cpu, tol) and _close(s.performance, performance, tol)):
            continue
        out = (1.0 if s.out_per_in is None else s.out_per_in) * input_hz
        cap = s.max_frequency_hz
        if cap is not None and s.step == "period":
            # one message passes per k arriving, k the fewest whose span reaches the period
            if cap <= 0:
                out = 0.0
            else:
                k = max(1, int(out // cap))
                while k * cap < out * (1.0 - 1e-9):
                    k += 1
                while k > 1 and (k - 1) * cap >= out * (1.0 - 1e-9):
                    k -= 1
                out = out / k
        elif cap is not None and cap < out:
            out = cap
        size = s.bytes_per_msg
        if size is None:
            size = (s.bandwidth_kBps * 1000.0 / s.frequency_hz
                    if s.frequency_hz and s.bandwidth_kBps is not None else 0.0)
        return Choice(j, need, s.performance, s.value, out, size * out / 1000.0, {}, input_hz=input_hz, setting=j)
    return None


def _copy_per_hz(system: System, node: Node, publisher: str) -> float | None:
    """CPU units per input message a hosted node run standalone pays for its own copy of its
    input: its container's ``copy_cpu_per_MBps`` x the largest bytes per message of the input
    topic over its publisher's settings (docs/formats.md, "membership"; this checker's own
    copy of the rule). None: it cannot run standalone."""
    host = system.node.get(node.container or "")
    if host is None or host.copy_cpu_per_MBps is None or node.input is None:
        return None
    largest = 0.0
    for s in system.node[publisher].settings:
        rate = s.topics.get(node.input)
        if rate is not None and rate.bandwidth_kBps is not None and rate.frequency_hz:
            size = 1000.0 * rate.bandwidth_kBps / rate.frequency_hz
        elif s.bytes_per_msg is not None:
            size = s.bytes_per_msg
        elif s.bandwidth_kBps is not None and s.frequency_hz:
            size = 1000.0 * s.bandwidth_kBps / s.frequency_hz
        else:
            continue
        largest = max(largest, size)
    return host.copy_cpu_per_MBps * largest / 1e6


def _copy_cpu(system: System, node: Node) -> float | None:
    """CPU units a hosted node that is not driven pays run standalone, for its own copies of
    what it receives: its container's ``copy_cpu_per_MBps`` x the MB/s of every edge into it,
    each at its publisher's setting that sends the most (this checker's own copy of the
    rule). None: it cannot run standalone."""
    host = system.node.get(node.container or "")
    if host is None or host.copy_cpu_per_MBps is None:
        return None
    into = 0.0
    for e in system.edges:
        if e.dst != node.name or e.src not in system.node:
            continue
        most = 0.0
        for s in system.node[e.src].settings:
            if e.bandwidth_kBps is not None:
                kbps = e.bandwidth_kBps
            elif e.topic is not None and e.topic in s.topics and s.topics[e.topic].bandwidth_kBps is not None:
                kbps = s.topics[e.topic].bandwidth_kBps or 0.0
            else:
                kbps = s.bandwidth_kBps or 0.0
            most = max(most, kbps)
        into += most
    return host.copy_cpu_per_MBps * into / 1000.0


def _topic_rate(choice: Choice, topic: str) -> float | None:
    rate = choice.topics.get(topic)
    if rate is not None and rate.frequency_hz is not None:
        return rate.frequency_hz
    return choice.frequency_hz


def _flow(system: System, plan: Plan, chosen: dict[str, Choice], tol: float) -> list[str]:
    """Match every driven node's setting at the input rate its publisher's planned setting
    gives, publishers first (a pass per level of the data flow); the problems found."""
    bad: list[str] = []
    publisher: dict[str, list[str]] = defaultdict(list)
    for n in system.nodes:
        for t in n.topics:
            publisher[t].append(n.name)
    pending = [n for n in system.nodes if n.input is not None and n.name in plan.nodes]
    while pending:
        later = []
        for node in pending:
            pubs = publisher.get(node.input or "", [])
            if len(pubs) != 1:
                bad.append(f"node {node.name}: input {node.input} has {len(pubs)} publishers, not 1")
                continue
            if pubs[0] not in chosen:
                later.append(node)
                continue
            f_in = _topic_rate(chosen[pubs[0]], node.input or "")
            pn = plan.nodes[node.name]
            if f_in is None:
                bad.append(f"node {node.name}: its input {node.input} has no rate at {pubs[0]}'s setting")
                continue
            copy = _copy_per_hz(system, node, pubs[0]) if pn.standalone else 0.0
            if copy is None:
                bad.append(f"node {node.name}: standalone, but it has no container with a copy price to leave")
                continue
            ch = _driven_choice(node, f_in, pn.cpu, pn.performance, tol, pn.value, copy)
            if ch is None:
                bad.append(f"node {node.name}: cpu {pn.cpu:g} / performance {pn.performance:g} is none of its "
                           f"settings at its input's rate {f_in:g} Hz")
                continue
            chosen[node.name] = ch
            if pn.input_hz is not None and not _close(pn.input_hz, f_in, tol):
                bad.append(f"node {node.name}: plan says input_hz {pn.input_hz:g}, {pubs[0]} publishes "
                           f"{node.input} at {f_in:g} Hz")
            for t, rate in pn.topics.items():
                if rate.frequency_hz is not None and not _close(rate.frequency_hz, ch.frequency_hz or 0.0, tol):
                    bad.append(f"node {node.name}: plan says topic {t} at {rate.frequency_hz:g} Hz, its input "
                               f"rate gives {ch.frequency_hz:g}")
        if len(later) == len(pending):
            bad.extend(f"node {n.name}: its input's publisher has no setting in the plan (or a cycle)" for n in later)
            break
        pending = later
    return bad


def plan_objective(system: System, plan: Plan, problem: int) -> float:
    """Eq 1 (Σ w·P with the system's normalised weights) or eq 2 (Σ server capacity)."""
    if problem == 1:
        return sum(system.node[n].weight * pn.performance for n, pn in plan.nodes.items() if n in system.node)
    total = 0.0
    for c in system.computers:
        if c.kind == "server":
            pc = plan.computers.get(c.name)
            total += (pc.capacity if pc is not None and pc.capacity is not None else 0.0)
    return total


def check_plan(system: System, plan: Plan, *, tol: float = 1e-6) -> list[str]:
    """The violated constraints of ``plan`` (an empty list: feasible and consistent)."""
    if plan.status == "infeasible":
        return [f"plan is infeasible: {plan.reason}"]
    problem = plan.problem
    bad: list[str] = []
    comps = system.computer

    # eq 5: every node placed exactly once, on an existing computer
    for extra in sorted(set(plan.nodes) - set(system.node)):
        bad.append(f"node {extra}: not in the system")
    chosen: dict[str, Choice] = {}
    where: dict[str, str] = {}
    for node in system.nodes:
        pn = plan.nodes.get(node.name)
        if pn is None:
            bad.append(f"node {node.name}: not placed")
            continue
        if pn.computer not in comps:
            bad.append(f"node {node.name}: on unknown computer {pn.computer}")
            continue
        where[node.name] = pn.computer
        # eq 8: residence
        if node.residence is not None and pn.computer not in node.residence:
            bad.append(f"node {node.name}: residence: on {pn.computer}, allowed {', '.join(node.residence)}")
        copy = _copy_cpu(system, node) if pn.standalone and node.input is None else 0.0
        if node.input is not None:
            pass  # matched at its input's rate, once its publisher's setting is known (_flow)
        elif copy is None:
            bad.append(f"node {node.name}: standalone, but it has no container with a copy price to leave")
        elif (ch := _node_choice(node, pn.cpu - copy, pn.performance, tol, pn.value)) is None:
            more = f" (with the copy of its inputs, {copy:g}, on top)" if copy else ""
            bad.append(f"node {node.name}: cpu {pn.cpu:g} / performance {pn.performance:g} is none of its "
                       f"settings{more}")
        else:
            chosen[node.name] = ch
        if not _close(pn.weight, node.weight, 1e-6):
            bad.append(f"node {node.name}: weight {pn.weight:g}, the system says {node.weight:g}")

    bad.extend(_flow(system, plan, chosen, tol))

    # eq 9: coresidence
    for node in system.nodes:
        for other in node.coresidence:
            if node.name in where and other in where and where[node.name] != where[other]:
                bad.append(f"coresidence: {node.name} on {where[node.name]} but {other} on {where[other]}")
    # membership: a node hosted by a container (nodelet manager) sits on its computer, unless
    # the plan runs it standalone, which only membership "choose" allows
    for node in system.nodes:
        host = node.container
        alone = node.name in plan.nodes and plan.nodes[node.name].standalone
        if alone and system.membership != "choose":
            bad.append(f"membership: {node.name} standalone, but the system's membership is {system.membership}")
        if alone and host is None:
            bad.append(f"membership: {node.name} standalone, but it has no container")
        if alone:
            continue
        if host is not None and node.name in where and host in where and where[node.name] != where[host]:
            bad.append(f"container: {node.name} on {where[node.name]} but its container {host} on {where[host]}")

    # eq 3: CPU per computer
    load: dict[str, float] = defaultdict(float)
    for n, comp in where.items():
        load[comp] += plan.nodes[n].cpu
    for c in system.computers:
        pc = plan.computers.get(c.name)
        if problem == 2 and c.kind == "server":
            cap = pc.capacity if pc is not None else None
            if cap is None:
                bad.append(f"computer {c.name}: Problem 2 plan gives the server no capacity")
                cap = 0.0
            if c.max_capacity is not None and _over(cap, c.max_capacity, tol):
                bad.append(f"computer {c.name}: sized {cap:g} > max_capacity {c.max_capacity:g}")
        else:
            cap = c.capacity if c.capacity is not None else 0.0
        if _over(load[c.name], cap, tol):
            bad.append(f"computer {c.name}: cpu {load[c.name]:g} > capacity {cap:g}")
        elif pc is not None and pc.margin and _over(load[c.name], cap - pc.margin, tol):
            bad.append(f"computer {c.name}: cpu {load[c.name]:g} leaves less than its margin {pc.margin:g} "
                       f"of capacity {cap:g} free")
        if pc is not None and not _close(pc.cpu, load[c.name], tol):
            bad.append(f"computer {c.name}: plan reports cpu {pc.cpu:g}, its nodes sum to {load[c.name]:g}")

    # eq 4: links and shared media
    link_load = [0.0] * len(system.links)
    for e in system.edges:
        if e.src not in where or e.dst not in where or e.src not in chosen:
            continue
        a, b = where[e.src], where[e.dst]
        if a == b:
            continue
        route = system.route(a, b)
        if route is None:
            bad.append(f"edge {e.src}->{e.dst}: no network path between {a} and {b}")
            continue
        bw = system.edge_bandwidth(e, chosen[e.src])
        for li in route:
            link_load[li] += bw
    for i, link in enumerate(system.links):
        if _over(link_load[i], link.bandwidth_kBps, tol):
            bad.append(f"link {link.between[0]}-{link.between[1]}: load {link_load[i]:g} "
                       f"> bandwidth {link.bandwidth_kBps:g} kB/s")
    for m in system.media:
        total = sum(link_load[i] for i, link in enumerate(system.links) if link.medium == m.name)
        if _over(total, m.bandwidth_kBps, tol):
            bad.append(f"medium {m.name}: load {total:g} > bandwidth {m.bandwidth_kBps:g} kB/s")
    reported = {tuple(pl.between): pl.load_kBps for pl in plan.links}
    for i, link in enumerate(system.links):
        got = reported.get(tuple(link.between))
        if got is not None and not _close(got, link_load[i], tol):
            bad.append(f"link {link.between[0]}-{link.between[1]}: plan reports load {got:g}, "
                       f"edges sum to {link_load[i]:g}")

    # latency budgets (system.yaml budget_ms) and the latency the plan states
    bad.extend(_latency(system, plan, where, link_load, tol))

    # eq 1 / eq 2: the objective
    if not bad or plan.objective is not None:
        want = plan_objective(system, plan, problem)
        if plan.objective is None or not math.isfinite(plan.objective) or not _close(plan.objective, want, tol):
            bad.append(f"objective: plan says {plan.objective}, eq {problem} gives {want:g}")
    return bad


# ---- latency budgets: this checker's own copy of the latency rule (docs/solvers.md "Latency";
# written apart from perfros_bag/system/latency.py) ------------------------------------------
def _speed(own_max: float, own_threads: float, others: list[tuple[float, float]], capacity: float) -> float:
    """CPU units a busy node (up to ``own_max``, ``own_threads`` slices) gets beside
    ``others`` ((need, threads)) on ``capacity``: the water level L of max-min fairness per
    thread (each gets min(need, threads x L)), found by bisection."""
    if own_max + sum(o for o, _ in others) <= capacity:
        return own_max
    lo, hi = 0.0, max([capacity, own_max, *(o for o, _ in others)])
    for _ in range(200):
        mid = (lo + hi) / 2
        if min(own_max, own_threads * mid) + sum(min(o, t * mid) for o, t in others) > capacity:
            hi = mid
        else:
            lo = mid
    return min(own_max, own_threads * lo)


def _busy_time(system: System, plan: Plan, node: str, comp: str, lam: float, capacity: float) -> float | None:
    """Seconds ``node`` runs for one message: every node of ``comp`` with its input gets the
    message at once and each asks for its threads' cores until its ``cpu / lam`` is done;
    the rest of ``comp`` asks for its planned CPU. Stepped from one finish to the next, each
    share from :func:`_speed` (the water level against everyone else's asks)."""
    topic = system.node[node].input
    upc = system.latency.units_per_core
    same = {n for n, q in plan.nodes.items()
            if q.computer == comp and n in system.node and system.node[n].input == topic}
    todo = {n: plan.nodes[n].cpu / lam for n in same}
    threads = {n: _threads(system.node[n], q.value) if n in system.node else 1.0 for n, q in plan.nodes.items()}
    fixed = [(q.cpu, threads[n]) for n, q in plan.nodes.items() if q.computer == comp and n not in same]
    clock = 0.0
    while node in todo:
        rates = {}
        for n in todo:
            asks = fixed + [(threads[m] * upc, threads[m]) for m in todo if m != n]
            rates[n] = _speed(threads[n] * upc, threads[n], asks, capacity)
        if rates[node] <= 0:
            return None
        step = min(todo[n] / r for n, r in rates.items() if r > 0)
        clock += step
        todo = {n: w - rates[n] * step for n, w in todo.items() if w - rates[n] * step > 1e-9 * max(w, 1e-12)}
    return clock


def _threads(node: Node, value: float | None) -> float:
    """Busy threads at a value: the setting's ``threads``, else the node's, else 1."""
    for s in node.settings:
        if value is not None and s.value is not None and math.isclose(s.value, value, rel_tol=1e-9, abs_tol=1e-9):
            if s.threads is not None:
                return max(1.0, s.threads)
            break
    return max(1.0, node.threads) if node.threads is not None else 1.0


def _waited(mean: float, rho: float, q: float) -> float:
    if mean <= 0 or rho <= 0 or rho <= 1 - q:
        return 0.0
    return mean / rho * math.log(rho / (1 - q))


def _chain_ms(system: System, plan: Plan, chain_topics: tuple[str, ...], where: dict[str, str],
              link_load: list[float]) -> tuple[float, float, list[tuple[float, float]]] | str:
    """(p50, p95, per hop (p50, p95)) in ms of a chain for the plan, or why it has none."""
    lat = system.latency
    total50 = total95 = 0.0
    hops: list[tuple[float, float]] = []
    for a, b in zip(chain_topics, chain_topics[1:], strict=False):
        nodes = [n for n in system.nodes if b in n.topics and n.input == a]
        pubs = [n for n in system.nodes if a in n.topics]
        if not nodes or not pubs:
            return f"hop {a} -> {b} cannot be followed"
        node, pub = nodes[0].name, pubs[0].name
        pn, pp = plan.nodes.get(node), plan.nodes.get(pub)
        if pn is None or pp is None or not pn.input_hz:
            return f"hop {a} -> {b}: its node or input rate is not in the plan"
        lam = pn.input_hz
        comp = pn.computer
        pc = plan.computers.get(comp)
        capacity = pc.capacity if pc is not None and pc.capacity is not None else sum(
            q.cpu for q in plan.nodes.values() if q.computer == comp)
        busy = _busy_time(system, plan, node, comp, lam, capacity)
        if busy is None:
            return f"hop {a} -> {b}: {node} gets no CPU"
        rho = lam * busy
        # a CFS-capped computer: an idle cgroup's first quota runs at once and the last ends
        # part-way into its period, one period sooner on average; never below the node's
        # time at its threads' speed, and not when saturated (no quota left over)
        quick = pn.cpu / lam / (_threads(system.node[node], pn.value) * lat.units_per_core)
        if lat.cfs_period_ms > 0 and rho <= 1 + 1e-9 and busy > quick:
            busy_burst = max(busy - lat.cfs_period_ms / 1000.0, quick)
        else:
            busy_burst = busy
        service = lat.service_scale.get(node, 1.0) * busy_burst
        # periodic input: a message finds the node idle up to rho 1 (at 1 within rounding: a node
        # getting exactly its planned CPU, a sized server); above, the drop-oldest queue is full
        # when the node takes its oldest: it waited queue_size - 1 periods and part of one (and
        # the backlog_msgs the socket buffers hold ahead of that queue)
        w50 = w95 = 0.0
        if rho > 1 + 1e-9:
            full = lat.queue_size + lat.backlog_msgs
            w50 = min((full - 0.5) / lam, full * service)
            w95 = min((full - 0.05) / lam, full * service)
        t50 = t95 = 0.0
        if pp.computer != comp:
            route = system.route(pp.computer, comp)
            if route is None:
                return f"hop {a} -> {b}: no path from {pp.computer} to {comp}"
            rate = pp.topics.get(a)
            hz = rate.frequency_hz if rate is not None else None
            kbps = rate.bandwidth_kBps if rate is not None else None
            size = kbps / hz if hz and kbps is not None else 0.0
            stream = size * (hz or 0.0)
            parts = [(system.links[li].bandwidth_kBps, link_load[li]) for li in route]
            for m in sorted({md for li in route if (md := system.links[li].medium) is not None}):
                parts.append((system.medium[m].bandwidth_kBps,
                              sum(link_load[i] for i, link in enumerate(system.links) if link.medium == m)))
            slowest = 0.0
            for bw, load in parts:
                t = size / (lat.link_efficiency * bw)
                burst = lat.link_burst_ms / 1000.0 if load < bw else 0.0  # a shaper's bucket, refilled
                slowest = max(slowest, t - burst, 0.0)
                u = min(max(load - stream, 0.0) / bw, 0.99)
                mean = lat.queue_factor * u * t / (2 * (1 - u))
                t50 += _waited(mean, u, 0.5)
                t95 += _waited(mean, u, 0.95)
            t50 += slowest
            t95 += slowest
        ratio = lat.node_p95_ratio.get(node, lat.p95_ratio)
        h50 = lat.overhead_ms + 1000 * (t50 + w50 + service)
        h95 = lat.overhead_ms + 1000 * (t95 + w95 + ratio * service)
        hops.append((h50, h95))
        total50 += h50
        total95 += h95
    return total50, total95, hops


def _latency(system: System, plan: Plan, where: dict[str, str], link_load: list[float], tol: float) -> list[str]:
    """Every budgeted chain within its budget, and every latency the plan states as this
    checker predicts it."""
    bad: list[str] = []
    stated = {c.get("name"): c for c in plan.chains}
    for chain in system.chains:
        said = stated.get(chain.name)
        if chain.budget_ms is None and said is None:
            continue
        got = _chain_ms(system, plan, chain.topics, where, link_load)
        if isinstance(got, str):
            if chain.budget_ms is not None:
                bad.append(f"chain {chain.name}: has a budget but {got}")
            continue
        p50, p95, hops = got
        for q, limit in chain.budget_ms.items() if chain.budget_ms is not None else []:
            value = p50 if q == "p50" else p95
            if _over(value, limit, tol):
                bad.append(f"chain {chain.name}: predicted {q} {value:.6g} ms > budget {limit:g} ms")
        pred = (said or {}).get("predicted_ms")
        if isinstance(pred, dict):
            for q, value in (("p50", p50), ("p95", p95)):
                if pred.get(q) is not None and not _close(float(pred[q]), value, max(tol, 1e-5)):
                    bad.append(f"chain {chain.name}: plan states {q} {pred[q]} ms, the model gives {value:.6g}")
    return bad
