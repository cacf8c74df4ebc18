"""Characterise a fleet's recordings on Dask, large single recordings split by chunk ranges.

:func:`characterise_on_dask` is what ``characterise --scheduler/--workers`` runs: every
recording is one task (``characterise_recording`` on a worker), except a large ROS 1 bag
or MCAP file (``split_bytes`` or more), which becomes one task per group of chunks
(:mod:`perfros_bag.ingest.split`). When the last part of a split recording is done, the
client merges the parts' statistics exactly and builds that recording's rows from them
(the CPU trace is read there; it is small). Outcomes come back one per recording, in
entry order, as :func:`~perfros_bag.characterisation.distributed.run_distributed` gives them, and the
progress callback is called once per finished recording.

With ``latency`` each part also returns its messages' header stamps, read in the same pass
(:func:`~perfros_bag.ingest.split.read_part_stamps`); the client concatenates them and
computes each topic's p50/p95/max from the whole sample
(:func:`~perfros_bag.ingest.contents.latencies`): the same numbers as from the whole file.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.characterisation.distributed import Outcome, ProgressCallback, run_distributed
from perfros_bag.characterisation.recording import characterise_recording, reporting
from perfros_bag.errors import PerfrosError
from perfros_bag.ingest.split import (
    TARGET_BYTES,
    Part,
    SplitPlan,
    merge_parts,
    merge_stamps,
    plan_split,
    read_part,
    read_part_stamps,
)

if TYPE_CHECKING:  # pragma: no cover
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.characterisation.manifest import RecordingEntry
    from perfros_bag.ingest.stats import RecordingStats
    from perfros_bag.system.types import System

#: Recordings at least this large are split; each task reads about ``PART_BYTES`` of file.
SPLIT_BYTES = 512 << 20
PART_BYTES = 128 << 20


@dataclass(frozen=True)
class Unit:
    """One task: a whole recording (``part`` None) or a part of entry ``index``."""

    index: int
    label: str  # unique: the entry's name, or "<name> [part k/n]"
    entry: RecordingEntry
    part: Part | None = None


def plan_units(entries: Sequence[RecordingEntry], *, fast: bool = True,
               split_bytes: int = SPLIT_BYTES, part_bytes: int = PART_BYTES,
               ) -> tuple[list[Unit], dict[int, SplitPlan]]:
    """The tasks, and the split plans of the recordings that were split."""
    units: list[Unit] = []
    plans: dict[int, SplitPlan] = {}
    for i, entry in enumerate(entries):
        path = entry.path
        if fast and path.is_file() and path.stat().st_size >= split_bytes:
            plan = plan_split(path)
            parts = plan.parts(part_bytes)
            if plan.format != "whole" and len(parts) > 1:
                plans[i] = plan
                units += [Unit(i, f"{entry.name} [part {k + 1}/{len(parts)}]", entry, part)
                          for k, part in enumerate(parts)]
                continue
        units.append(Unit(i, entry.name, entry))
    return units, plans


def run_unit(unit: Unit, system: System | None, fast: bool, latency: bool = False) -> Any:
    """On a worker: a recording's rows, or a part's partial statistics (with ``latency``,
    and its header stamps)."""
    if unit.part is not None:
        return read_part_stamps(unit.part) if latency else read_part(unit.part)
    with reporting(unit.entry):  # the local loop's wording for an unforeseen exception
        return characterise_recording(unit.entry, system, fast=fast, latency=latency)


def _merged_rows(entry: RecordingEntry, plan: SplitPlan, values: list[Any], system: System | None,
                 fast: bool, latency: bool) -> list[Row]:
    """A split recording's rows from its parts' outcomes (read again whole when a part could
    not be read from its index)."""
    if not latency:
        return characterise_recording(entry, system, fast=fast, stats=merge_parts(plan, values))
    if any(v is None for v in values):
        return characterise_recording(entry, system, fast=fast, latency=True)
    from perfros_bag.ingest.contents import latencies

    stats = merge_parts(plan, [v[0] for v in values])
    if stats.messages != sum(v[0].messages for v in values):  # merge_parts read the whole file
        return characterise_recording(entry, system, fast=fast, stats=stats, latency=True)
    types: dict[str, Any] = {}
    for v in values:
        for topic, tt in v[2].items():
            types.setdefault(topic, tt)
    delays = latencies(entry.path, merge_stamps([v[1] for v in values]), types)
    return characterise_recording(entry, system, fast=fast, stats=stats, latency=True, delays=delays)


def characterise_on_dask(entries: Sequence[RecordingEntry], system: System | None, *,
                         fast: bool = True, scheduler: str | None = None,
                         workers: int | None = None,
                         progress: ProgressCallback | None = None,
                         split_bytes: int = SPLIT_BYTES,
                         part_bytes: int = PART_BYTES,
                         latency: bool = False) -> list[Outcome[list[Row]]]:
    """One outcome (rows or error) per entry, in entry order; ``latency``: with the
    ``latency_*`` columns."""
    entries = list(entries)
    units, plans = plan_units(entries, fast=fast, split_bytes=split_bytes, part_bytes=part_bytes)
    by_label = {u.label: k for k, u in enumerate(units)}
    parts: dict[int, dict[int, Outcome[Any]]] = {i: {} for i in plans}  # entry -> unit no -> outcome
    expected = {i: sum(1 for u in units if u.index == i) for i in plans}
    done: dict[int, Outcome[list[Row]]] = {}

    def merge(i: int) -> Outcome[list[Row]]:
        entry = entries[i]
        outcomes = [parts[i][k] for k in sorted(parts[i])]  # chunk order
        failed = next((o for o in outcomes if o.error is not None), None)
        if failed is not None:
            return Outcome(entry.name, error=failed.error)
        try:
            with reporting(entry):
                rows = _merged_rows(entry, plans[i], [o.value for o in outcomes], system, fast, latency)
        except PerfrosError as exc:
            return Outcome(entry.name, error=exc)
        return Outcome(entry.name, value=rows)

    def on_unit(outcome: Outcome[Any]) -> None:
        k = by_label[outcome.label]
        i = units[k].index
        if units[k].part is None:
            done[i] = outcome
        else:
            parts[i][k] = outcome
            if len(parts[i]) < expected[i]:
                return
            done[i] = merge(i)
        if progress is not None:
            progress(done[i])

    run_distributed(units, partial(run_unit, system=system, fast=fast, latency=latency),
                    scheduler=scheduler, workers=workers, progress=on_unit,
                    label=lambda u: u.label)
    return [done[i] for i in range(len(entries))]


def read_split(path: str | Path, *, scheduler: str | None = None, workers: int | None = None,
               target_bytes: int = TARGET_BYTES, progress: bool = False) -> RecordingStats:
    """``read_recording(path)``, its chunk ranges read as parallel tasks
    (:mod:`perfros_bag.ingest.split`)."""
    plan = plan_split(path)
    outcomes = run_distributed(plan.parts(target_bytes), read_part, scheduler=scheduler,
                               workers=workers, progress=progress, description="chunks")
    for outcome in outcomes:
        if outcome.error is not None:
            raise outcome.error
    return merge_parts(plan, [o.value for o in outcomes])
