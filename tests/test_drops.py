"""Runs where a driven node was overloaded and dropped part of its input
(perfros_bag/fitting/drops.py), against a message-by-message simulation of a node behind
ROS's drop-oldest queue of one message: which runs are told apart, the rate each processed,
and what ``init``'s draft and ``fit`` make of them (a line through the processed rates,
recomputed with numpy)."""

from __future__ import annotations

import numpy as np
import pytest

from perfros_bag.fitting.build import DrivenSample, _driven_measure
from perfros_bag.fitting.drops import OUTPUT_ROSE, RunRates, dropped_share, processed_hz, split_runs
from perfros_bag.sweep.driven import RunMeasure, draft_settings, find_inputs
from perfros_bag.sweep.graph import Graph, GraphNode, GraphTopic


def simulate(input_hz: float, service_s: float, out_per_in: float = 1.0, span_s: float = 60.0) -> float:
    """The output rate of a node that takes ``service_s`` per message, fed at ``input_hz``
    through a queue of one message (a newer message replaces the waiting one)."""
    period = 1.0 / input_hz
    busy_until, waiting, processed = 0.0, None, 0
    t = 0.0
    while t < span_s:
        if waiting is not None and busy_until <= t:  # the queued message starts when the node frees up
            busy_until, waiting, processed = max(busy_until, waiting) + service_s, None, processed + 1
        if busy_until <= t:
            busy_until, processed = t + service_s, processed + 1
        else:
            waiting = t  # drop-oldest: the newest message waits
        t += period
    return out_per_in * processed / span_s


CPU_BASE, CPU_PER_HZ = 2.0, 4.0  # the node's CPU: base + per processed message


def _runs(inputs: list[float], service_s: float, out_per_in: float = 1.0) -> list[RunRates]:
    out = []
    for f in inputs:
        f_out = simulate(f, service_s, out_per_in)
        out.append(RunRates(f, f_out, CPU_BASE + CPU_PER_HZ * f_out / out_per_in))
    return out


def test_a_node_that_keeps_up_keeps_every_run() -> None:
    runs = _runs([5.0, 10.0, 20.0], service_s=0.03)  # capacity 33 Hz
    drops = split_runs(runs)
    assert drops.kept == (0, 1, 2) and drops.overloaded == () and drops.follows


@pytest.mark.parametrize("out_per_in", [1.0, 0.5])
def test_a_node_past_its_capacity_is_overloaded_and_processed_what_the_simulation_says(out_per_in: float) -> None:
    service = 1 / 15  # capacity 15 Hz
    inputs = [5.0, 10.0, 20.0, 40.0]
    runs = _runs(inputs, service, out_per_in)
    drops = split_runs(runs)
    assert drops.kept == (0, 1) and drops.overloaded == (2, 3) and drops.follows
    for i in drops.overloaded:
        simulated = simulate(inputs[i], service) / 1.0
        assert processed_hz(runs, drops, i) == pytest.approx(simulated, rel=0.02)
        assert dropped_share(runs, drops, i) == pytest.approx(1 - simulated / inputs[i], abs=0.02)
    for i in drops.kept:
        assert processed_hz(runs, drops, i) == inputs[i] and dropped_share(runs, drops, i) == 0


def test_a_node_on_its_own_clock_does_not_follow() -> None:
    runs = [RunRates(5.0, 10.0, 3.0), RunRates(20.0, 10.0, 3.0)]  # 10 Hz whatever comes in
    drops = split_runs(runs)
    assert not drops.follows and drops.overloaded == ()


def test_a_run_whose_output_barely_rose_is_an_overload_only_when_its_cpu_followed_what_it_processed() -> None:
    runs = [RunRates(5.0, 5.0, 3.0), RunRates(20.0, 5.9, 2.6)]  # x1.18 <= x1.2, CPU 27 % below 0.6 x 5.9
    assert not split_runs(runs).follows
    runs = [RunRates(5.0, 5.0, 3.0), RunRates(20.0, 5.1, 3.06)]  # x1.02: within a rate's noise (a clock)
    assert not split_runs(runs).follows
    runs = [RunRates(5.0, 5.0, 3.0), RunRates(20.0, 5.9, 3.5)]  # x1.18, CPU 0.6 per message: starved
    assert split_runs(runs).overloaded == (1,)
    runs = [RunRates(5.0, 5.0, 3.0), RunRates(20.0, 6.1, 3.5)]  # x1.22
    assert split_runs(runs).overloaded == (1,)
    runs = [RunRates(5.0, 5.0, 3.0), RunRates(20.0, 5.9, None)]  # no CPU: only the rates' rule (x1.2)
    assert not split_runs(runs).follows


def test_a_node_starved_by_the_machine_is_overloaded_at_the_rate_the_simulation_processed() -> None:
    """A heavy node that gets a third of the CPU it needs for 7.5 Hz (the machine busy with
    other work): its capacity falls to 3 Hz, its output barely rises past its lowest input's
    (x1.11 < x1.2), its CPU follows what it processed."""
    service = 1 / 3.0
    inputs = [2.7, 5.0, 7.5]
    runs = _runs(inputs, service)
    drops = split_runs(runs)
    assert drops.kept == (0,) and drops.overloaded == (1, 2)
    assert all(runs[i].output_hz < OUTPUT_ROSE * runs[0].output_hz for i in (1, 2))  # not the x1.2 rule
    for i in drops.overloaded:
        assert processed_hz(runs, drops, i) == pytest.approx(simulate(inputs[i], service), rel=1e-9)


def test_issue_31s_flow_node_as_swept_is_overloaded_not_a_node_of_its_own() -> None:
    """fback_flow's runs on fixtures/throttle_edges at load 11 (input Hz, output Hz, CPU
    units; 2026-11-27 20:33): kept at 2.7 Hz, starved at 5 and 7.5 Hz."""
    runs = [RunRates(2.729, 2.716, 14.527), RunRates(2.707, 2.722, 14.319), RunRates(2.660, 2.653, 14.885),
            RunRates(5.002, 2.849, 16.785), RunRates(5.001, 3.132, 19.483), RunRates(5.000, 3.703, 19.228),
            RunRates(7.602, 2.898, 14.412), RunRates(7.501, 3.244, 18.714), RunRates(7.503, 3.361, 19.588)]
    drops = split_runs(runs)
    assert drops.kept == (0, 1, 2) and drops.overloaded == (3, 4, 5, 6, 7, 8)
    # swept again at load 14 (21:14): starved at 2.7 Hz and 5 Hz in too, below the kept runs' output
    runs = [RunRates(2.707, 2.734, 14.75), RunRates(2.644, 2.649, 15.22), RunRates(2.749, 2.469, 11.80),
            RunRates(4.967, 2.520, 11.87), RunRates(5.004, 5.069, 28.23), RunRates(4.998, 5.028, 26.77),
            RunRates(7.500, 2.924, 19.97), RunRates(7.608, 2.507, 12.81), RunRates(7.560, 4.510, 38.77)]
    drops = split_runs(runs)
    assert drops.kept == (0, 1, 4, 5) and drops.overloaded == (2, 3, 6, 7, 8)


def test_a_clock_slower_than_every_input_is_not_taken_for_a_starved_node() -> None:
    """One output rate (within 3 %) at 2.7, 5 and 7.5 Hz in, its CPU per output message the
    same: a node on its own 2.5 Hz clock, not a driven one."""
    runs = [RunRates(2.7, 2.50, 5.0), RunRates(5.0, 2.52, 5.1), RunRates(7.5, 2.49, 5.0)]
    assert not split_runs(runs).follows


def test_an_overload_that_used_less_cpu_is_not_an_overload() -> None:
    runs = [RunRates(5.0, 5.0, 3.0), RunRates(20.0, 12.0, 2.0)]
    assert not split_runs(runs).follows
    runs = [RunRates(5.0, 5.0, None), RunRates(20.0, 12.0, 2.0)]  # CPU not measured: the rates decide
    assert split_runs(runs).overloaded == (1,)


def _graph() -> Graph:
    return Graph((GraphNode("/camera", None, None), GraphNode("/detector", None, None)),
                 (GraphTopic("/image", None, ("/camera",), ("/detector",)),
                  GraphTopic("/found", None, ("/detector",), ())))


class _Node:
    def __init__(self, name: str, topics: tuple[str, ...]) -> None:
        self.name, self.topics = name, topics


def test_init_drafts_an_overloaded_detector_as_driven_with_its_line_through_the_processed_rates() -> None:
    """A replay sweep at x0.5, x1, x2 of a 10 Hz camera: the detector (capacity 15 Hz) drops
    at x2. It is drafted as driven, its ratio from the runs it kept up with, and its CPU line
    (least squares, numpy) through the rates it processed: the simulated node's own line."""
    service, inputs = 1 / 15, [5.0, 10.0, 20.0]
    runs = _runs(inputs, service, out_per_in=1.0)
    names = ["x0.5", "x1", "x2"]
    camera = {n: RunMeasure(None, 1.0, {"/image": (r.input_hz, 2000.0)}) for n, r in zip(names, runs, strict=True)}
    detector = {n: RunMeasure(None, r.cpu, {"/found": (r.output_hz, r.output_hz * 0.1)})
                for n, r in zip(names, runs, strict=True)}
    found = find_inputs([_Node("camera", ("/image",)), _Node("detector", ("/found",))], _graph(),
                        {"camera": camera, "detector": detector}, {"camera": "/camera", "detector": "/detector"})
    follow = found["detector"]
    assert follow.topic == "/image" and set(follow.overloaded) == {"x2"}
    assert follow.overloaded["x2"] == pytest.approx(simulate(20.0, service), rel=1e-9)
    (setting,) = draft_settings(("/found",), detector, follow).values()
    processed = [simulate(f, service) for f in inputs]
    slope, base = np.polyfit(processed, [r.cpu for r in runs], 1)
    assert setting.cpu == pytest.approx(base, abs=1e-6) and setting.cpu_per_hz == pytest.approx(slope, rel=1e-6)
    assert setting.cpu_per_hz == pytest.approx(CPU_PER_HZ, rel=1e-6)
    assert setting.out_per_in == pytest.approx(1.0, rel=1e-9)
    # without the rule the x2 run's ratio (0.75) is 33 % off the others: nothing would be drafted
    assert runs[2].ratio < 0.8


def test_fit_leaves_the_overloaded_run_out_of_the_ratio_and_counts_its_cpu_at_the_processed_rate() -> None:
    service, inputs = 1 / 15, [5.0, 10.0, 20.0, 30.0]
    runs = _runs(inputs, service, out_per_in=0.5)
    samples = [DrivenSample(f"r{i}", r.input_hz, r.cpu, r.output_hz, r.output_hz * 0.2) for i, r in enumerate(runs)]
    m = _driven_measure(None, samples, cap=None)
    processed = [simulate(f, service) for f in inputs]
    slope, base = np.polyfit(processed, [r.cpu for r in runs], 1)
    assert m.cpu == pytest.approx(base, abs=1e-6) and m.cpu_per_hz == pytest.approx(slope, rel=1e-6)
    assert m.out_per_in == pytest.approx(0.5, rel=1e-9)
    assert sum("overloaded" in n for n in m.notes) == 2
