"""Runs where a driven node dropped part of its input because it could not keep up.

A node that follows its input keeps one output/input ratio while it has the CPU for every
message. Offered more than it can process (a sweep run at a high input rate, on a loaded
machine), ROS's drop-oldest queue throws the surplus away: its output still rises with its
input, but less than in proportion, and its ratio falls. Such a run says nothing about the
node's ratio, and its CPU was spent on the messages it processed, not on those offered.

The rule (one copy, used by ``init``'s draft and by ``fit``), per own setting of the node:

- the **kept** runs are those whose ratio lies within :data:`RATIO_TOLERANCE` of the best
  ratio at that setting (best / ratio <= 1.10);
- a run below that is **overloaded** when its output still followed its input: there is a
  kept run at a lower input rate whose output it exceeds by more than :data:`OUTPUT_ROSE`
  (x1.2), and whose CPU it does not fall below (where both were measured);
- a run below that is also **overloaded** when the machine starved it (other processes took
  the CPU it needed: its output then sits near what it could process, whatever its input):
  the node's outputs over the runs at this setting are not all within :data:`OUTPUT_MOVED`
  (3 %, beyond a rate's measurement noise) of one another (so it is not on a clock of its
  own), this run's output stayed at or below its input, and its CPU is what the kept runs'
  CPU per message gives for the messages it processed (output / the kept mean ratio) within
  :data:`CPU_MATCH` (25 %: a starved node's CPU over an 8 s run on a loaded machine). Seen on
  issue 31's layout: opencv_apps' fback_flow behind a throttle, swept at machine load 11 on 2
  cores, put out 2.7 Hz at 2.7 Hz in and 2.8-3.7 Hz at 5 and 7.5 Hz in, at 5.0-6.2 CPU units per frame against 5.3-5.6
  in the kept runs; deployed at load 8 it kept up with 7.5 Hz. A node on its own clock slower
  than every input it got keeps one output rate (within the noise) in every run, which is
  what tells it apart here;
- any other run means the node does not keep one ratio to this input (a node on its own
  clock: its output stays put while its input moves).

An overloaded run's CPU counts at the rate it **processed**: its input rate times its ratio
over the kept runs' mean ratio (:func:`processed_hz`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

#: the output/input ratios of the runs kept at one setting stay within this factor (max / min)
RATIO_TOLERANCE = 1.10
#: an overloaded run's output exceeds a kept run's at a lower input rate by more than this factor
OUTPUT_ROSE = 1.2
#: a node's outputs at one setting that all lie within this factor of one another keep a clock
OUTPUT_MOVED = 1.03
#: a starved run's CPU lies within this share of the kept runs' CPU per message x what it processed
CPU_MATCH = 0.25


@dataclass(frozen=True)
class RunRates:
    """One run of a node at one own setting: its input rate, its output rate, its CPU."""

    input_hz: float
    output_hz: float
    cpu: float | None = None

    @property
    def ratio(self) -> float:
        return self.output_hz / self.input_hz


@dataclass(frozen=True)
class Drops:
    """The runs at one setting split by the rule of this module (indices into its input)."""

    kept: tuple[int, ...]
    overloaded: tuple[int, ...]
    #: runs neither kept nor overloaded: the node does not keep one ratio to this input
    other: tuple[int, ...]

    @property
    def follows(self) -> bool:
        return not self.other


def split_runs(runs: Sequence[RunRates]) -> Drops:
    """Kept, overloaded and other runs (the module's rule); runs without a positive input or
    output rate are ``other``."""
    valid = [i for i, r in enumerate(runs) if r.input_hz > 0 and r.output_hz > 0]
    if not valid:
        return Drops((), (), tuple(range(len(runs))))
    best = max(runs[i].ratio for i in valid)
    kept = [i for i in valid if best / runs[i].ratio <= RATIO_TOLERANCE]
    overloaded, other = [], [i for i in range(len(runs)) if i not in valid]
    for i in valid:
        if i in kept:
            continue
        r = runs[i]
        if any(runs[j].input_hz < r.input_hz and r.output_hz > OUTPUT_ROSE * runs[j].output_hz
               and _not_less_cpu(r.cpu, runs[j].cpu) for j in kept) or _starved(runs, kept, i):
            overloaded.append(i)
        else:
            other.append(i)
    return Drops(tuple(kept), tuple(overloaded), tuple(sorted(other)))


def _starved(runs: Sequence[RunRates], kept: Sequence[int], i: int) -> bool:
    """Was run ``i`` (below the kept ratio) starved of CPU: the outputs at its setting moved
    (:data:`OUTPUT_MOVED`), its own stayed at or below its input, and its CPU matches the kept
    runs' CPU per message for what it processed (:data:`CPU_MATCH`)? Needs CPU everywhere."""
    r = runs[i]
    if r.cpu is None or r.output_hz > r.input_hz or any(runs[j].cpu is None for j in kept):
        return False
    outputs = [x.output_hz for x in runs if x.output_hz > 0]
    if max(outputs) <= OUTPUT_MOVED * min(outputs):
        return False  # one output rate whatever came in: a clock of its own
    per_message = sum(runs[j].cpu or 0.0 for j in kept) / sum(runs[j].input_hz for j in kept)
    ratio = sum(runs[j].ratio for j in kept) / len(kept)
    want = per_message * r.output_hz / ratio
    return want > 0 and abs(r.cpu - want) <= CPU_MATCH * want


def _not_less_cpu(a: float | None, b: float | None) -> bool:
    return a is None or b is None or a >= b


def kept_ratio(runs: Sequence[RunRates], drops: Drops) -> float:
    """The mean output/input ratio over the kept runs."""
    return sum(runs[i].ratio for i in drops.kept) / len(drops.kept)


def processed_hz(runs: Sequence[RunRates], drops: Drops, i: int) -> float:
    """The rate at which run ``i`` processed its input: its input rate for a kept run, its
    input rate x its ratio / the kept mean ratio for an overloaded one."""
    r = runs[i]
    if i not in drops.overloaded:
        return r.input_hz
    return r.input_hz * r.ratio / kept_ratio(runs, drops)


def dropped_share(runs: Sequence[RunRates], drops: Drops, i: int) -> float:
    """The share of its input that run ``i`` dropped (0 for a kept run)."""
    return 1.0 - processed_hz(runs, drops, i) / runs[i].input_hz
