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


def _system(rate: float, work_units: float, capacity: float, queue_size: int, backlog: float) -> System:
    return parse_system(yaml.safe_load(f"""
computers:
  - {{name: source, kind: robot, capacity: 100}}
  - {{name: box, kind: server, capacity: {capacity}}}
links:
  - {{between: [source, box], bandwidth_kBps: 1.0e+12}}
latency: {{overhead_ms: 0, p95_ratio: 1.0, queue_size: {queue_size}, backlog_msgs: {backlog}}}
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
