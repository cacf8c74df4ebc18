"""Characterise a fleet's recordings on Dask, large single recordings split by chunk ranges.

:func:`characterise_on_dask` is what ``characterise --scheduler/--workers`` runs: every
recording is one task (``characterise_recording`` on a worker), except a large ROS 1 bag
or MCAP file (``split_bytes`` or more), which becomes one task per group of chunks
(:mod:`perfros_bag.ingest.split`). When the last part of a split recording is done, the
client merges the parts' statistics exactly and builds that recording's rows from them
(the CPU trace is read there; it is small). Outcomes come back one per recording, in
entry order, as :func:`~perfros_bag.characterisation.distributed.run_distributed` gives them, and the
progress callback is called once per finished recording.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import partial
from typing import TYPE_CHECKING, Any

from perfros_bag.characterisation.distributed import Outcome, ProgressCallback, run_distributed
from perfros_bag.characterisation.recording import characterise_recording, reporting
from perfros_bag.errors import PerfrosError
from perfros_bag.ingest.split import Part, SplitPlan, merge_parts, plan_split, read_part

if TYPE_CHECKING:  # pragma: no cover
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.characterisation.manifest import RecordingEntry
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


def run_unit(unit: Unit, system: System | None, fast: bool) -> Any:
    """On a worker: a recording's rows, or a part's partial statistics."""
    if unit.part is not None:
        return read_part(unit.part)
    with reporting(unit.entry):  # the local loop's wording for an unforeseen exception
        return characterise_recording(unit.entry, system, fast=fast)


def characterise_on_dask(entries: Sequence[RecordingEntry], system: System | None, *,
                         fast: bool = True, scheduler: str | None = None,
                         workers: int | None = None,
                         progress: ProgressCallback | None = None,
                         split_bytes: int = SPLIT_BYTES,
                         part_bytes: int = PART_BYTES) -> list[Outcome[list[Row]]]:
    """One outcome (rows or error) per entry, in entry order."""
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
                stats = merge_parts(plans[i], [o.value for o in outcomes])
                rows = characterise_recording(entry, system, fast=fast, stats=stats)
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

    run_distributed(units, partial(run_unit, system=system, fast=fast),
                    scheduler=scheduler, workers=workers, progress=on_unit,
                    label=lambda u: u.label)
    return [done[i] for i in range(len(entries))]
