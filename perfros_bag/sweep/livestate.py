"""``DIR/live.json``: what a ``deploy --out DIR`` in progress runs, so ``watch --deployment DIR``
can attach to it (format ``perfros-bag/deploy-live@1``, docs/formats.md "live.json").

``deploy`` writes it (atomically) once every node is up, placed and capped, and removes it
when the run ends, on success, error or Ctrl-C. It names the deploy's own PID (a file left
by a deploy that was killed outright is recognised as stale), the master's URI and the
computer whose network namespace it is reached from, the namespaces and cgroups per
computer, the cores each cgroup is capped at, and each launched node's PID and computer.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.fileio import atomic_write_json, read_json

LIVE_FILE = "live.json"
LIVE_FORMAT = "perfros-bag/deploy-live@1"


@dataclass
class LiveState:
    run_id: str
    pid: int  # the deploy's own process
    master_uri: str
    master_computer: str | None  # whose namespace reaches the master (None: the host's)
    plan: str
    system: str | None = None
    units_per_core: float = 100.0
    namespaces: dict[str, str] = field(default_factory=dict)  # computer -> netns name
    cgroups: dict[str, str] = field(default_factory=dict)  # computer -> cgroup directory
    cores: dict[str, float] = field(default_factory=dict)  # computer -> cores of its cap
    capped: bool = False
    nodes: dict[str, dict[str, Any]] = field(default_factory=dict)  # ROS node -> {pid, computer}
    links: list[dict[str, Any]] = field(default_factory=list)  # {between, bandwidth_kBps} in force now
    values: dict[str, Any] = field(default_factory=dict)  # system node -> the value it runs at now
    plan_in_force: str | None = None  # the last plan control.json applied (None: the deploy's own)
    #: ROS node -> when (seconds since the epoch) the deploy began restarting it for a new plan;
    #: empty once every restart of that plan is done
    restarting: dict[str, float] = field(default_factory=dict)
    restart_timeout_s: float | None = None  # the longest a restart may take before the deploy fails
    folder: str | None = None  # the deploy's --out (where it was read from; not written)

    def running(self) -> bool:
        """Whether the deploy that wrote it still runs."""
        return _alive(self.pid)

    def to_dict(self) -> dict[str, Any]:
        return {"format": LIVE_FORMAT, "run_id": self.run_id, "pid": self.pid, "master_uri": self.master_uri,
                "master_computer": self.master_computer, "plan": self.plan, "system": self.system,
                "units_per_core": self.units_per_core, "namespaces": dict(self.namespaces),
                "cgroups": dict(self.cgroups), "cores": dict(self.cores), "capped": self.capped,
                "nodes": dict(self.nodes), "links": list(self.links), "values": dict(self.values),
                "plan_in_force": self.plan_in_force, "restarting": dict(self.restarting),
                "restart_timeout_s": self.restart_timeout_s}


def write_live(path: Path, state: LiveState) -> None:
    atomic_write_json(path, state.to_dict())


def read_live(folder: str | Path) -> LiveState:
    """The live state of the deploy running into ``folder``; an :class:`InputError` when there
    is none (no deploy, one that has not started its nodes yet, or one that ended or was killed)."""
    path = Path(folder) / LIVE_FILE
    if not path.is_file():
        raise InputError(folder, f"no deploy in progress here (no {LIVE_FILE}: not started, still starting, "
                                 "or ended)")
    data = read_json(path)
    if not isinstance(data, dict) or data.get("format") != LIVE_FORMAT:
        raise InputError(path, f"not a deploy's live state (format {LIVE_FORMAT} expected)")
    try:
        state = LiveState(
            run_id=str(data["run_id"]), pid=int(data["pid"]), master_uri=str(data["master_uri"]),
            master_computer=data.get("master_computer"), plan=str(data["plan"]), system=data.get("system"),
            units_per_core=float(data.get("units_per_core", 100.0)),
            namespaces={str(k): str(v) for k, v in (data.get("namespaces") or {}).items()},
            cgroups={str(k): str(v) for k, v in (data.get("cgroups") or {}).items()},
            cores={str(k): float(v) for k, v in (data.get("cores") or {}).items()},
            capped=bool(data.get("capped", False)),
            nodes={str(k): dict(v) for k, v in (data.get("nodes") or {}).items()},
            links=[dict(x) for x in (data.get("links") or [])],
            values={str(k): v for k, v in (data.get("values") or {}).items()},
            plan_in_force=data.get("plan_in_force"),
            restarting={str(k): float(v) for k, v in (data.get("restarting") or {}).items()},
            restart_timeout_s=None if data.get("restart_timeout_s") is None else float(data["restart_timeout_s"]),
            folder=str(folder))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"damaged live state: {exc}") from None
    if not state.running():
        raise InputError(path, f"stale: the deploy that wrote it (pid {state.pid}) is not running")
    return state


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True
