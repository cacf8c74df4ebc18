"""``tune.json`` (format ``perfros-bag/tune@1``, docs/formats.md): the one reader and writer.

The document is plain JSON written atomically after every finished round, so a run that is
interrupted or fails keeps every round it finished, and a new start resumes after them.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
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

    capacity: float | None
    cpu_planned: float | None
    cpu_measured: float | None
    throttled_share: float
    starved: bool

    def to_json(self) -> dict[str, Any]:
        return {"capacity": self.capacity, "cpu_planned": self.cpu_planned, "cpu_measured": self.cpu_measured,
                "throttled_share": self.throttled_share, "starved": self.starved}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RoundComputer:
        return cls(d.get("capacity"), d.get("cpu_planned"), d.get("cpu_measured"), d.get("throttled_share", 0.0),
                   bool(d.get("starved", False)))


@dataclass
class RoundNode:
    """A node of a round (tune.json ``rounds[].nodes``): predicted vs measured CPU and how the
    refit uses its recording (``refit``: measured, rescaled to its planned rate, left out)."""

    computer: str | None
    value: Any
    cpu_planned: float | None
    cpu_measured: float | None
    kept_ratio: float | None
    starved: bool
    cpu_need: float | None
    cpu_factor: float | None
    refit: str | None
    input_hz: float | None = None
    model_cpu_before: float | None = None
    model_cpu_after: float | None = None

    def to_json(self) -> dict[str, Any]:
        return {"computer": self.computer, "value": self.value, "cpu_planned": self.cpu_planned,
                "cpu_measured": self.cpu_measured, "kept_ratio": self.kept_ratio, "starved": self.starved,
                "cpu_need": self.cpu_need, "cpu_factor": self.cpu_factor, "refit": self.refit,
                "input_hz": self.input_hz, "model_cpu_before": self.model_cpu_before,
                "model_cpu_after": self.model_cpu_after}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> RoundNode:
        return cls(d.get("computer"), d.get("value"), d.get("cpu_planned"), d.get("cpu_measured"),
                   d.get("kept_ratio"), bool(d.get("starved", False)), d.get("cpu_need"), d.get("cpu_factor"),
                   d.get("refit"), d.get("input_hz"), d.get("model_cpu_before"), d.get("model_cpu_after"))


@dataclass
class TuneRound:
    """One finished round of the loop (tune.json ``rounds[]``, docs/formats.md "tune"): what it
    deployed, eq 10 expected vs measured, and per computer and node what the refit learned."""

    round: int
    dir: str
    plan: str | None
    model: str | None
    refit_model: str | None
    objective: float | None
    values: dict[str, Any]
    placement: dict[str, str]
    expected: float
    measured: float
    deviation_pct: float
    within_tolerance: bool | None
    run_id: str | None
    cpu_cap: str | None
    network: str | None
    computers: dict[str, RoundComputer]
    nodes: dict[str, RoundNode]

    @property
    def recording(self) -> str:
        """Its recording as the refit's manifest names it (and so its rows' ``recording``)."""
        return f"{self.dir}/run.bag"

    def to_json(self) -> dict[str, Any]:
        return {"round": self.round, "dir": self.dir, "plan": self.plan, "model": self.model,
                "refit_model": self.refit_model, "objective": self.objective, "values": self.values,
                "placement": self.placement, "expected": self.expected, "measured": self.measured,
                "deviation_pct": self.deviation_pct, "within_tolerance": self.within_tolerance,
                "run_id": self.run_id, "cpu_cap": self.cpu_cap, "network": self.network,
                "computers": {c: v.to_json() for c, v in self.computers.items()},
                "nodes": {n: v.to_json() for n, v in self.nodes.items()}}

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
