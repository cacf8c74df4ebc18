"""``init``: which nodes follow their input, and how (system.yaml ``input:``, docs/formats.md
"init: driven nodes").

The rule: a node is driven by a topic it subscribes to (graph.yaml) and that exactly one
other drafted node publishes when, over the runs,

- the topic's measured rate varied by more than :data:`INPUT_VARIED` (max / min > 1.2) among
  the runs at one of the node's own settings (its own parameter's value; the one setting of a
  node that was not varied), and
- at every own setting, every output topic of the node that publishes at a rate kept one
  ratio to it: all ``F_out / F_in`` of its topics over the runs at that setting within
  :data:`RATIO_TOLERANCE` of each other (max / min <= 1.10), leaving out the runs where the
  node was overloaded and dropped part of its input (its output still rose with its input:
  :mod:`perfros_bag.fitting.drops`, the one copy of that rule, which ``fit`` uses too).

A subscriber whose output keeps its own clock fails the second test (its ratio changes as
much as the input's rate did: more than 20 % > 10 %), and a node with no output at a rate is
never driven (nothing shows it follows). Several qualifying topics: the steadiest ratio wins;
a choice that would close a cycle of inputs is not made. A subscriber that fails the ratio
test may still be a **throttle** of the topic, its value capping its output
(:func:`throttle_rule`; drafted with ``max_frequency_hz`` and ``step``, :func:`draft_throttle`).

Per own setting, from the runs at it:

- ``cpu`` + ``cpu_per_hz`` x F_in: the least-squares line through (the rate it processed:
  the measured input rate, or for an overloaded run that rate less what it dropped, CPU) when
  the input rate varied there by more than 20 %; a negative base is clipped to 0 (the line
  then goes through the origin: ``cpu_per_hz = sum(F C) / sum(F^2)``) and a negative slope to 0
  (``cpu`` = the mean CPU), and the draft says so in a comment (the line is ``fit``'s own,
  :func:`perfros_bag.fitting.build.cpu_line`);
- otherwise (one-at-a-time: the own parameter varied at one input rate) the line of the
  reference setting (the own setting with a line, the one with most runs), scaled by this
  setting's CPU over the line's CPU at the input rate it was measured at: ``k = mean C /
  (cpu_ref + cpu_per_hz_ref x mean F_in)``, ``cpu = k cpu_ref``, ``cpu_per_hz = k
  cpu_per_hz_ref``. It reproduces the measured CPU there, stays >= 0, and assumes the own
  parameter scales the per-message work and the base alike;
- ``out_per_in`` = the mean of ``F_out / F_in`` (its topics that publish at a rate, the runs
  not overloaded);
- ``bytes_per_msg`` = the mean over the runs of ``bandwidth x 1000 / F_out`` (all its topics'
  bandwidth, F_out the mean rate of its topics).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from perfros_bag.characterisation.table import Row
    from perfros_bag.sweep.graph import Graph

from perfros_bag.fitting.drops import RATIO_TOLERANCE, RunRates, processed_hz, split_runs

#: The input's rate must vary by more than this factor (max / min) among runs at one own setting.
INPUT_VARIED = 1.2


@dataclass
class RunMeasure:
    """One node in one run: its own value, CPU and each topic's (frequency, bandwidth)."""

    value: Any
    cpu: float | None = None
    topics: dict[str, tuple[float | None, float | None]] = field(default_factory=dict)

    def rate(self, topic: str) -> float:
        f = self.topics.get(topic, (None, None))[0]
        return f if f is not None else 0.0


def per_run(rows: Sequence[Row]) -> dict[str, dict[str, RunMeasure]]:
    """node -> recording -> what that run measured of it."""
    out: dict[str, dict[str, RunMeasure]] = {}
    for r in rows:
        if not r.node:
            continue
        m = out.setdefault(r.node, {}).setdefault(r.recording, RunMeasure(r.value))
        if r.cpu_units_mean is not None:
            m.cpu = r.cpu_units_mean
        if r.topic:
            m.topics[r.topic] = (r.frequency_hz, r.bandwidth_kBps)
    return out


@dataclass(frozen=True)
class Follow:
    """A driven node: its input topic, the node publishing it, and per recording the input's rate."""

    topic: str
    publisher: str
    input_hz: dict[str, float]
    spread: float  # the largest max / min of its output/input ratios over its own settings
    #: a throttle (its setting caps its output, :func:`throttle_rule`): ``"period"`` or
    #: ``"min"`` (how the cap acts), None for a node that keeps one ratio to its input
    throttle: str | None = None
    #: recording -> the input rate it processed, for the runs where the node was overloaded
    #: and dropped part of its input (:mod:`perfros_bag.fitting.drops`)
    overloaded: Mapping[str, float] = field(default_factory=dict)

    def processed(self, rec: str) -> float:
        """The input rate the node processed in recording ``rec``."""
        return self.overloaded.get(rec, self.input_hz[rec])


def _groups(runs: Mapping[str, RunMeasure]) -> dict[str, list[str]]:
    """own value (repr) -> the recordings at it."""
    out: dict[str, list[str]] = {}
    for rec, m in runs.items():
        out.setdefault(repr(m.value), []).append(rec)
    return out


def rated_topics(topics: Sequence[str], runs: Mapping[str, RunMeasure]) -> list[str]:
    """The node's topics that published at a rate in some run."""
    return [t for t in topics if any(m.rate(t) > 0 for m in runs.values())]


def _varied(rates: Sequence[float]) -> bool:
    return len(rates) > 1 and min(rates) > 0 and max(rates) / min(rates) > INPUT_VARIED


def _follows(topics: Sequence[str], runs: Mapping[str, RunMeasure],
             input_hz: Mapping[str, float]) -> tuple[float, dict[str, float]] | None:
    """The largest spread (max / min) of the output/input ratios over the own settings (runs
    where the node was overloaded left out) and those runs' processed input rates, or None
    when the node does not follow this input (docstring of the module)."""
    groups = _groups(runs)
    if not topics or not any(_varied([input_hz[r] for r in recs]) for recs in groups.values()):
        return None
    worst, overloaded = 1.0, {}
    for recs in groups.values():
        if any(runs[r].rate(t) <= 0 for r in recs for t in topics):
            return None
        rates = [RunRates(input_hz[r], sum(runs[r].rate(t) for t in topics) / len(topics), runs[r].cpu)
                 for r in recs]
        drops = split_runs(rates)
        if not drops.follows:
            return None
        ratios = [runs[recs[i]].rate(t) / input_hz[recs[i]] for i in drops.kept for t in topics]
        worst = max(worst, max(ratios) / min(ratios))
        overloaded.update({recs[i]: processed_hz(rates, drops, i) for i in drops.overloaded})
    return (worst, overloaded) if worst <= RATIO_TOLERANCE else None


def find_inputs(nodes: Sequence[Any], graph: Graph, measured: Mapping[str, Mapping[str, RunMeasure]],
                ros_name: Mapping[str, str]) -> dict[str, Follow]:
    """The drafted nodes (``nodes``: the skeleton's, with ``name`` and ``topics``) that follow
    one of their subscriptions, by the rule of this module; ``ros_name``: drafted name -> ROS name."""
    publisher = {t: n.name for n in nodes for t in n.topics}
    out: dict[str, Follow] = {}
    for n in nodes:
        runs = measured.get(n.name, {})
        topics = rated_topics(n.topics, runs)
        best: Follow | None = None
        for g in graph.topics:
            source = publisher.get(g.name)
            if ros_name[n.name] not in g.subscribers or source is None or source == n.name:
                continue
            if sum(g.name in m.topics for m in nodes) != 1 or _closes_cycle(n.name, source, out):
                continue
            upstream = measured.get(source, {})
            input_hz = {r: upstream[r].rate(g.name) for r in runs if r in upstream}
            if not runs or len(input_hz) != len(runs) or min(input_hz.values()) <= 0:
                continue  # a run without the input at a rate shows nothing to follow
            follows = _follows(topics, runs, input_hz)
            if follows is not None and (best is None or best.throttle is not None or follows[0] < best.spread):
                best = Follow(g.name, source, input_hz, follows[0], overloaded=follows[1])
            elif best is None and (rule := throttle_rule(topics, runs, input_hz)) is not None:
                best = Follow(g.name, source, input_hz, rule[1], rule[0])
        if best is not None:
            out[n.name] = best
    return out


def _closes_cycle(node: str, source: str, inputs: Mapping[str, Follow]) -> bool:
    """Would ``node`` driven by ``source``'s topic close a cycle of inputs?"""
    seen: set[str] = set()
    while source not in seen:
        if source == node:
            return True
        seen.add(source)
        if source not in inputs:
            return False
        source = inputs[source].publisher
    return False


@dataclass(frozen=True)
class DrivenSetting:
    """A driven node's setting as drafted (system.yaml keys) and what was clipped."""

    value: Any
    cpu: float
    cpu_per_hz: float
    out_per_in: float
    bytes_per_msg: float
    clipped: str | None = None  # what was clipped at 0 (the fit's words), None when nothing
    scaled_from: Any = None  # the reference value (one-at-a-time), None when its own line


def _line(f: Sequence[float], c: Sequence[float]) -> tuple[float, float, str | None]:
    """Least squares C = a + b F, clipped (a >= 0, then through the origin; b >= 0): the fit's
    own line (:func:`perfros_bag.fitting.build.cpu_line`), with what was clipped."""
    from perfros_bag.fitting.build import cpu_line

    a, b, _r2, notes = cpu_line(list(zip(f, c, strict=True)))
    return a, b, "; ".join(notes) or None


def draft_settings(topics: Sequence[str], runs: Mapping[str, RunMeasure], follow: Follow) -> dict[str, DrivenSetting]:
    """own value (``repr``) -> its drafted setting, by the module's rules."""
    from perfros_bag.fitting.build import scaled_line

    rated = rated_topics(topics, runs)
    groups = _groups(runs)
    lines: dict[str, tuple[float, float, str | None]] = {}
    for key, recs in groups.items():
        if _varied([follow.input_hz[r] for r in recs]):
            lines[key] = _line([follow.processed(r) for r in recs], [runs[r].cpu or 0.0 for r in recs])
    ref = max(lines, key=lambda k: len(groups[k]))  # find_inputs made sure one exists
    out = {}
    for key, recs in groups.items():
        cpus = [runs[r].cpu or 0.0 for r in recs]
        ratios = [runs[r].rate(t) / follow.input_hz[r] for r in recs for t in rated if r not in follow.overloaded]
        sizes = []
        for r in recs:
            f_out = sum(runs[r].rate(t) for t in rated) / len(rated)
            bw = sum(b for _f, b in runs[r].topics.values() if b is not None)
            sizes.append(bw * 1000.0 / f_out)
        if key in lines:
            a, b, clipped = lines[key]
            scaled = None
        else:
            a_ref, b_ref, _ = lines[ref]
            f_in = sum(follow.processed(r) for r in recs) / len(recs)
            a, b = scaled_line((a_ref, b_ref), f_in, sum(cpus) / len(cpus))
            clipped, scaled = None, runs[groups[ref][0]].value
        out[key] = DrivenSetting(runs[recs[0]].value, a, b, sum(ratios) / len(ratios), sum(sizes) / len(sizes),
                                 clipped, scaled)
    return out


# --- throttles: a setting that caps the output (docs/formats.md "init: throttles") ---------

#: a throttle's rule must give every run's output within this share of what it measured
THROTTLE_TOLERANCE = 0.10


def _rule_error(step: str | None, value: float, f_in: float, f_out: float) -> float | None:
    """How far ``f_out`` lies from the throttle rule's output (a share of it) at cap
    ``value`` and input ``f_in``; where a period throttle is ambiguous (a whole ratio n), 0
    anywhere between its two steps F_in / (n + 1) and F_in / n, else from the nearer. None
    when the rule gives no output."""
    from perfros_bag.system.types import Setting, driven_rates, step_ambiguous

    s = Setting(0.0, 0.0, max_frequency_hz=value, step="period" if step == "period" else None)
    want = driven_rates(s, f_in)[1]
    if step_ambiguous(s, f_in):
        n = max(round(f_in / value), 1)
        lo, hi = f_in / (n + 1), f_in / n
        return 0.0 if lo <= f_out <= hi else min(abs(f_out - lo) / lo, abs(f_out - hi) / hi)
    return abs(f_out - want) / want if want > 0 else None


def throttle_rule(topics: Sequence[str], runs: Mapping[str, RunMeasure],
                  input_hz: Mapping[str, float]) -> tuple[str, float] | None:
    """``(rule, worst error)`` when the node is a throttle of this input, else None.

    A throttle: its own values are numbers > 0 and at least two of them ran, its output
    moved with them (the mean output rate over its own values varied by more than
    :data:`INPUT_VARIED`) and never ran above its input (2 % of measurement allowed), and one
    rule with the value as its cap gives every run's output of every rated topic within
    :data:`THROTTLE_TOLERANCE`: ``"period"`` (topic_tools/throttle: F_in / ceil(F_in /
    value); at a whole ratio either neighbouring step) or ``"min"`` (min(F_in, value)).
    Where both do, the smaller worst error wins, the period rule on a tie."""
    groups = _groups(runs)
    values = [runs[recs[0]].value for recs in groups.values()]
    if not topics or len(groups) < 2 or not all(isinstance(v, int | float) and v > 0 for v in values):
        return None
    means = [sum(runs[r].rate(t) for r in recs for t in topics) / (len(recs) * len(topics))
             for recs in groups.values()]
    if min(means) <= 0 or max(means) / min(means) <= INPUT_VARIED:
        return None
    if any(runs[r].rate(t) > 1.02 * input_hz[r] for r in runs for t in topics):
        return None
    best: tuple[str, float] | None = None
    for rule in ("period", "min"):
        errors = [_rule_error(rule, float(runs[r].value), input_hz[r], runs[r].rate(t)) for r in runs for t in topics]
        worst = max((e if e is not None else float("inf")) for e in errors)
        if worst <= THROTTLE_TOLERANCE and (best is None or worst < best[1]):
            best = (rule, worst)
    return best


def draft_throttle(topics: Sequence[str], runs: Mapping[str, RunMeasure], follow: Follow) -> dict[str, DrivenSetting]:
    """A throttle's settings: per own value, the CPU line over its input rate (the fit's own,
    :func:`perfros_bag.fitting.build.cpu_line`: with one input rate, ``cpu`` 0 and all its CPU
    per input Hz), ``out_per_in`` the mean F_out / F_in of the runs its cap did not reach
    (1 when it reached every one: a throttle passes each message it keeps unchanged) and
    ``bytes_per_msg`` as for any driven node; the cap (its value) and rule are the caller's."""
    from perfros_bag.fitting.build import cpu_line

    rated = rated_topics(topics, runs)
    out = {}
    for key, recs in _groups(runs).items():
        value = runs[recs[0]].value
        a, b, _r2, notes = cpu_line([(follow.input_hz[r], runs[r].cpu or 0.0) for r in recs])
        free = [runs[r].rate(t) / follow.input_hz[r] for r in recs for t in rated
                if follow.input_hz[r] < 0.98 * value]
        sizes = []
        for r in recs:
            f_out = sum(runs[r].rate(t) for t in rated) / len(rated)
            bw = sum(b for _f, b in runs[r].topics.values() if b is not None)
            sizes.append(bw * 1000.0 / f_out)
        out[key] = DrivenSetting(value, a, b, sum(free) / len(free) if free else 1.0, sum(sizes) / len(sizes),
                                 "; ".join(notes) or None)
    return out
