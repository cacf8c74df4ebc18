"""``tune.json`` (format ``perfros-bag/tune@1``, docs/formats.md): the one reader and writer.

The document is plain JSON written atomically after every finished round, so a run that is
interrupted or fails keeps every round it finished, and a new start resumes after them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import DOCUMENT_KINDS, atomic_write_json, expect_kind, read_json
from perfros_bag.limits import tree_problem

TUNE_FORMAT = "perfros-bag/tune@1"
#: why the loop stopped (``stopped.reason``)
STOP_REASONS = ("within tolerance", "plan unchanged", "rounds")
_ROUND_KEYS = ("round", "dir", "values", "placement", "expected", "measured", "deviation_pct",
               "within_tolerance", "nodes", "computers")


@dataclass
class RoundComputer:
    """A computer of a round (tune.json ``rounds[].computers``): its cap, planned and measured
    CPU, and whether its cgroup was starved (throttled in enough CFS periods)."""

    capacity: float | None  # its CPU cap in the run (units)
    cpu_planned: float | None  # the plan's load on it (validation.json ``cpu_expected``)
    cpu_measured: float | None  # its nodes' CPU from the trace; None without one
    throttled_share: float  # share of the CFS periods its cgroup was throttled in
    starved: bool  # throttled_share >= THROTTLED_SHARE (tune/loop.py)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)  # the fields in tune.json's key order

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RoundComputer:
        return cls(d.get("capacity"), d.get("cpu_planned"), d.get("cpu_measured"), d.get("throttled_share", 0.0),
                   bool(d.get("starved", False)))


@dataclass
class RoundNode:
    """A node of a round (tune.json ``rounds[].nodes``): predicted vs measured CPU and how the
    refit uses its recording (``refit``: measured, rescaled to its planned rate, left out)."""

    computer: str | None  # where the plan put it
    value: Any  # its parameter's value as deployed (None: a node without a parameter)
    cpu_planned: float | None  # the plan's CPU at that value
    cpu_measured: float | None  # validation.json's, from the CPU trace
    kept_ratio: float | None  # its kept share of its planned rate (kept_share); None: no rate to compare
    starved: bool  # its computer was starved
    cpu_need: float | None  # what the refit takes: cpu_measured x cpu_factor; None when left out
    cpu_factor: float | None  # 1, or 1 / kept_ratio for a starved node rescaled to its planned rate
    refit: str | None  # how the refit uses its row: measured, rescaled to its planned rate, left out
    input_hz: float | None = None  # a driven node's planned input rate, else None
    model_cpu_before: float | None = None  # model k-1's CPU at the deployed value (and input rate)
    model_cpu_after: float | None = None  # model k's, filled after the refit

    def to_json(self) -> dict[str, Any]:
        return asdict(self)  # the fields in tune.json's key order

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RoundNode:
        return cls(d.get("computer"), d.get("value"), d.get("cpu_planned"), d.get("cpu_measured"),
                   d.get("kept_ratio"), bool(d.get("starved", False)), d.get("cpu_need"), d.get("cpu_factor"),
                   d.get("refit"), d.get("input_hz"), d.get("model_cpu_before"), d.get("model_cpu_after"))


@dataclass
class TuneRound:
    """One finished round of the loop (tune.json ``rounds[]``, docs/formats.md "tune"): what it
    deployed, eq 10 expected vs measured, and per computer and node what the refit learned."""

    round: int  # 1, 2, ...
    dir: str  # its folder under the loop's, ``round-K``
    plan: str | None  # its plan.json, relative to the loop's folder
    model: str | None  # the model it was solved on (model-(K-1).json)
    refit_model: str | None  # the model refitted with its recording (model-K.json)
    objective: float | None  # the plan's
    values: dict[str, Any]  # what its deployment set (deploy.json ``values``)
    placement: dict[str, str]  # node -> computer
    expected: float  # eq 10's Σ w·P planned
    measured: float  # and measured
    deviation_pct: float
    within_tolerance: bool | None  # the round holds (:func:`~perfros_bag.tune.loop.holds`)
    run_id: str | None  # deploy.json's
    cpu_cap: str | None  # how CPU was capped (deploy.json ``cpu_cap.mode``)
    network: str | None  # how links were shaped (deploy.json ``network.mode``)
    computers: dict[str, RoundComputer]
    nodes: dict[str, RoundNode]

    @property
    def recording(self) -> str:
        """Its recording as the refit's manifest names it (and so its rows' ``recording``)."""
        return f"{self.dir}/run.bag"

    def to_json(self) -> dict[str, Any]:
        """The round as tune.json holds it: the fields in its key order, computers and nodes too."""
        return asdict(self)

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> TuneRound:
        """A round as :func:`read_tune` checked it (its ``_ROUND_KEYS`` present)."""
        return cls(d["round"], d["dir"], d.get("plan"), d.get("model"), d.get("refit_model"), d.get("objective"),
                   dict(d["values"]), dict(d["placement"]), d["expected"], d["measured"], d["deviation_pct"],
                   d["within_tolerance"], d.get("run_id"), d.get("cpu_cap"), d.get("network"),
                   {c: RoundComputer.from_json(v) for c, v in d["computers"].items()},
                   {n: RoundNode.from_json(v) for n, v in d["nodes"].items()})


def write_tune(path: str | Path, document: dict[str, Any]) -> None:
    """Write tune.json atomically (a reader never sees half of it)."""
    atomic_write_json(path, document)


def read_tune(path: str | Path) -> dict[str, Any]:
    """Read tune.json, checking what the loop, its table and the report rely on."""
    data = read_json(path)
    kind = DOCUMENT_KINDS[TUNE_FORMAT]
    expect_kind(path, data, kind, {kind})
    if not isinstance(data, dict) or data.get("format") != TUNE_FORMAT:
        raise InputError(path, f"not a perfros-bag tune document (expected format {TUNE_FORMAT!r})")
    rounds = data.get("rounds")
    if not isinstance(rounds, list):
        raise InputError(path, "'rounds' must be a list")
    for i, r in enumerate(rounds):
        where = f"rounds[{i}]"
        if not isinstance(r, dict):
            raise InputError(path, f"{where}: must be an object")
        missing = [k for k in _ROUND_KEYS if k not in r]
        if missing:
            raise InputError(path, f"{where}: missing {', '.join(map(repr, missing))}")
        if r["round"] != i + 1:
            raise InputError(path, f"{where}: 'round' must be {i + 1}, got {r['round']!r}")
        if not isinstance(r["nodes"], dict) or not isinstance(r["computers"], dict):
            raise InputError(path, f"{where}: 'nodes' and 'computers' must be objects")
        for part in ("nodes", "computers"):
            bad = next((name for name, v in r[part].items() if not isinstance(v, dict)), None)
            if bad is not None:
                raise InputError(path, f"{where}.{part}.{bad}: must be an object")
        problem = tree_problem(r, where)
        if problem is not None:
            raise InputError(path, problem)
    stopped = data.get("stopped")
    if stopped is not None and (not isinstance(stopped, dict) or stopped.get("reason") not in STOP_REASONS):
        raise InputError(path, f"'stopped' must be null or name a reason ({', '.join(STOP_REASONS)})")
    return data
