"""The latency model's node wait and service (system/latency.py) against a discrete-event
simulation, written here, of what a deployment runs: a periodic source into ROS's drop-oldest
subscriber queue of a single-threaded node in a CFS-capped cgroup (at most ``quota`` of run
time in every CFS period, the rest of the period stalled)."""

from __future__ import annotations

import math
from collections import deque

import pytest
import yaml

from perfros_bag.system.latency import predict_chain
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import System

CFS_PERIOD = 0.010  # deploy's CFS period (rosrun/cgroups.py)


def simulate(period: float, work: float, quota: float, cfs_period: float, queue_size: int,
             n: int = 600) -> list[float]:
    """Delivered messages' latencies (s): arrivals every ``period`` (s); each needs ``work``
    seconds of one core; the group runs at most ``quota`` s per ``cfs_period``; a full queue
    drops its oldest message when a new one comes; the node takes its queue's oldest."""
    arrivals = [i * period for i in range(n)]
    t, i, used, period_end = 0.0, 0, 0.0, cfs_period
    queue: deque[float] = deque()
    job: list[float] | None = None  # [arrival, work left]
    out: list[float] = []
    eps = 1e-12
    while i < n or queue or job is not None:
        if job is None and queue:
            job = [queue.popleft(), work]
        events = [period_end] + ([arrivals[i]] if i < n else [])
        running = job is not None and used < quota - eps
        if running:
            assert job is not None
            events.append(t + min(job[1], quota - used))
        nxt = min(events)
        if running:
            assert job is not None
            job[1] -= nxt - t
            used += nxt - t
        t = nxt
        if job is not None and job[1] <= eps:
            out.append(t - job[0])
            job = None
        if t >= period_end - eps:
            used, period_end = 0.0, period_end + cfs_period
        if i < n and t >= arrivals[i] - eps:
            if len(queue) == queue_size:
                queue.popleft()
            queue.append(arrivals[i])
            i += 1
    return out


def quantile(xs: list[float], q: float) -> float:
    xs = sorted(xs)
    k = (len(xs) - 1) * q
    lo, hi = math.floor(k), math.ceil(k)
    return xs[lo] + (xs[hi] - xs[lo]) * (k - lo)


def _system(rate: float, work_units: float, capacity: float, queue_size: int, backlog: float,
            cfs_period_ms: float = 0) -> System:
    return parse_system(yaml.safe_load(f"""
computers:
  - {{name: source, kind: robot, capacity: 100}}
  - {{name: box, kind: server, capacity: {capacity}}}
links:
  - {{between: [source, box], bandwidth_kBps: 1.0e+12}}
latency: {{overhead_ms: 0, p95_ratio: 1.0, queue_size: {queue_size}, backlog_msgs: {backlog},
          cfs_period_ms: {cfs_period_ms}}}
nodes:
  - name: camera
    weight: 0.5
    topics: [/image]
    residence: [source]
    settings: [{{cpu: 1, performance: 100, frequency_hz: {rate}, bandwidth_kBps: 100}}]
  - name: node
    weight: 0.5
    input: /image
    topics: [/out]
    residence: [box]
    settings: [{{cpu: 0, cpu_per_hz: {work_units}, performance: 100, bytes_per_msg: 10}}]
edges:
  - {{from: camera, to: node, topic: /image}}
chains:
  - {{name: c, topics: [/image, /out]}}
"""))


# (input Hz, CPU units x s per message, the node's computer's capacity, queue_size, backlog):
# below and above utilisation 1, CFS caps from 15 to 50 % of a core, input periods that are
# no multiple of the CFS period (the phase of each message against CFS's periods moves). The
# backlog (socket buffers, first in first out ahead of the drop-oldest queue) holds its
# messages in the simulation as a longer queue: saturated, both are full and the node takes
# the oldest of all they hold.
CASES = [(9.963, 2.0, 50, 1, 0), (9.963, 2.0, 25, 1, 0), (4.98, 1.0, 15, 1, 2), (7.47, 2.0, 30, 1, 2),
         (9.963, 6.0, 50, 1, 0), (9.963, 3.0, 20, 1, 0), (9.963, 3.0, 20, 2, 0), (9.963, 6.0, 50, 3, 0),
         (9.963, 3.0, 20, 1, 2), (4.98, 3.0, 10, 2, 1)]


@pytest.mark.parametrize(("rate", "work", "capacity", "queue_size", "backlog"), CASES)
def test_node_wait_and_service_match_a_simulated_capped_node(rate: float, work: float, capacity: float,
                                                             queue_size: int, backlog: int) -> None:
    system = _system(rate, work, capacity, queue_size, backlog)
    node = system.node["node"]
    choice = {"camera": system.node["camera"].choices()[0], "node": system.driven_choice(node, 0, rate)}
    got = predict_chain(system, system.chains[0], {"camera": "source", "node": "box"}, choice,
                        {"source": 100, "box": capacity})
    hop = got.hops[0]
    lat = simulate(1 / rate, work / 100, capacity / 100 * CFS_PERIOD, CFS_PERIOD, queue_size + backlog)
    # the model's node part (service + wait) within one CFS period of the simulation: a capped
    # node runs in bursts of its quota, so a message ends up to one period before its mean
    for q, model in ((0.5, hop.service_ms + hop.wait_ms), (0.95, hop.service_ms + hop.wait_p95_ms)):
        assert 1000 * quantile(lat, q) == pytest.approx(model, abs=1000 * CFS_PERIOD), (q, hop)
    # and the regime: below utilisation 1 no message waits, above the queue is full
    rho = rate * work / capacity
    assert hop.utilisation == pytest.approx(rho)
    if rho < 1:
        assert hop.wait_ms == hop.wait_p95_ms == 0 and len(lat) == 600
    else:
        assert len(lat) < 600 * 0.99  # the drop-oldest queue lost messages


def test_the_old_m_d_1_wait_is_what_the_simulation_refutes() -> None:
    """At utilisation 0.8, M/D/1 (random arrivals) predicts a p95 wait of ~2.4 services; the
    periodic source of the simulation never waits: its p95 is within one CFS period of S."""
    rate, work, capacity = 9.963, 2.0, 25
    s = work / capacity
    rho = rate * s
    mean = rho * s / (2 * (1 - rho))
    md1_p95 = mean / rho * math.log(rho / 0.05)
    lat = simulate(1 / rate, work / 100, capacity / 100 * CFS_PERIOD, CFS_PERIOD, 1)
    assert quantile(lat, 0.95) <= s + CFS_PERIOD < s + md1_p95 - 10 * CFS_PERIOD


def _node_p50(rate: float, work: float, capacity: float, queue_size: int, backlog: int, cfs_period_ms: float) -> float:
    system = _system(rate, work, capacity, queue_size, backlog, cfs_period_ms)
    choice = {"camera": system.node["camera"].choices()[0],
              "node": system.driven_choice(system.node["node"], 0, rate)}
    hop = predict_chain(system, system.chains[0], {"camera": "source", "node": "box"}, choice,
                        {"source": 100, "box": capacity}).hops[0]
    return hop.service_ms + hop.wait_ms


# below utilisation 1 (the CASES above, and the case study's smoothing: 1.42 units x s per
# frame at 5.7 Hz on a 15-unit robot; a light node; a 45-unit server at 3 Hz)
IDLE_CASES = [c for c in CASES if c[0] * c[1] < c[2]] + [(5.7, 1.42, 15, 1, 2), (5.7, 0.6, 15, 1, 2),
                                                         (3.0, 3.0, 45, 1, 2)]


@pytest.mark.parametrize(("rate", "work", "capacity", "queue_size", "backlog"), IDLE_CASES)
def test_a_capped_node_that_finds_its_cgroup_idle_ends_one_period_sooner(
        rate: float, work: float, capacity: float, queue_size: int, backlog: int) -> None:
    """With ``cfs_period_ms`` (the computers are CFS-capped cgroups) the model's p50 is within
    half a CFS period of the simulation below utilisation 1, and closer than the fluid rule
    (``cfs_period_ms`` 0), which runs the node at its share all along and so ends later."""
    lat = simulate(1 / rate, work / 100, capacity / 100 * CFS_PERIOD, CFS_PERIOD, queue_size + backlog)
    sim = 1000 * quantile(lat, 0.5)
    quick = _node_p50(rate, work, capacity, queue_size, backlog, 1000 * CFS_PERIOD)
    fluid = _node_p50(rate, work, capacity, queue_size, backlog, 0)
    assert quick == pytest.approx(sim, abs=0.5 * 1000 * CFS_PERIOD)
    assert abs(quick - sim) < abs(fluid - sim)
    assert fluid - quick == pytest.approx(1000 * CFS_PERIOD)  # one period, as the rule says


def test_a_node_that_runs_uncapped_or_saturated_gets_no_head_start() -> None:
    """Where the node runs at its threads' speed (the cap is above it) or above utilisation 1
    (no quota left at any period's start), the period changes nothing."""
    for rate, work, capacity in ((5.0, 1.5, 150), (9.963, 3.0, 20)):
        assert _node_p50(rate, work, capacity, 1, 2, 10) == _node_p50(rate, work, capacity, 1, 2, 0)
