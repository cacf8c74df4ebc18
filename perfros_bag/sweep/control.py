"""``DIR/control.json``: a new plan for a ``deploy --out DIR`` in progress (format
``perfros-bag/deploy-control@1``, docs/formats.md "control.json").

``watch --deployment DIR --adapt`` writes it (atomically) with a sequence number and the
new plan's path. The deploy reads it about four times a second while it records
(:class:`Control`, ``record_run``'s ``on_tick``); on a new sequence number it restarts only
the nodes whose value or computer the new plan changes (with the launch file's arguments and
parameters of the new values, in the new computer's namespace and cgroup), and keeps the
master and every other node running. The caps are set again from the new plan's computers
(in place: the cgroups' quota); the links keep their rates (a re-plan keeps the system's
links). Each application is one entry of ``deploy.json`` ``replans``; the validation at the
end is against the plan in force then (the last one applied).

A control file may also change the emulated world instead of (or beside) the plan:
``links``, a list of ``{"between": [a, b], "bandwidth_kBps": x}``, re-shapes those links in
place (``tc qdisc change`` on their running qdiscs, :meth:`Network.set_link_rate`): what a
degrading wifi does to a robot. ``live.json`` then names every link's rate in force.
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping
from collections.abc import Set as AbstractSet
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import PerfrosError, PerfrosWarning
from perfros_bag.fileio import atomic_write_json, read_json

if TYPE_CHECKING:
    from perfros_bag.rosrun.cgroups import CpuGroups
    from perfros_bag.rosrun.network import Network
    from perfros_bag.sweep.nodelets import Nodelet
    from perfros_bag.sweep.runner import Restarter
    from perfros_bag.sweep.space import Run, Space
    from perfros_bag.system.plan import Plan

CONTROL_FILE = "control.json"
CONTROL_FORMAT = "perfros-bag/deploy-control@1"


def write_control(folder: str | Path, seq: int | None, plan_path: str | Path | None, why: list[str], *,
                  links: list[dict[str, Any]] | None = None) -> int:
    """Write ``folder/control.json``; ``seq`` None: one more than the file's present one.
    Returns the sequence number written."""
    if seq is None:
        seq = control_seq(folder) + 1
    doc: dict[str, Any] = {"format": CONTROL_FORMAT, "seq": seq, "why": why}
    if plan_path is not None:
        doc["plan"] = str(Path(plan_path).absolute())
    if links:
        doc["links"] = links
    atomic_write_json(Path(folder) / CONTROL_FILE, doc)
    return seq


def control_seq(folder: str | Path) -> int:
    """The sequence number of ``folder/control.json`` (0 when there is none or it is not one)."""
    try:
        doc = read_json(Path(folder) / CONTROL_FILE)
    except (PerfrosError, OSError):
        return 0
    seq = doc.get("seq") if isinstance(doc, dict) else None
    return seq if isinstance(seq, int) and not isinstance(seq, bool) else 0


def changed_nodes(old: Run, new: Run, old_where: dict[str, str], new_where: dict[str, str],
                  old_alone: AbstractSet[str] = frozenset(), new_alone: AbstractSet[str] = frozenset()) -> list[str]:
    """The system nodes whose value or computer differs between two runs of a plan, or that
    one plan runs standalone and the other does not (``*_alone``: plan.json ``standalone``)."""
    names = sorted(set(old.values) | set(new.values) | set(old_where) | set(new_where) | set(old_alone)
                   | set(new_alone))
    return [n for n in names if old.values.get(n) != new.values.get(n) or old_where.get(n) != new_where.get(n)
            or (n in old_alone) != (n in new_alone)]


@dataclass
class Control:
    """The deploy's side: polls ``folder/control.json`` and applies a new plan."""

    folder: Path
    space: Space
    arg_defaults: dict[str, str | None]
    run: Run  # what runs now
    where: dict[str, str]  # system node -> computer, now
    groups: CpuGroups
    units_per_core: float
    cap: bool  # set the new plan's caps (deploy --cap)
    on_applied: Callable[[dict[str, int]], None] | None = None  # ROS node -> new PID
    network: Network | None = None  # the emulated links (``links`` entries re-shape them)
    plan_path: str | None = None  # the plan in force (the last applied)
    #: called with the ROS nodes about to be restarted for a new plan, before the first is stopped
    on_restarting: Callable[[list[str]], None] | None = None
    #: the launch file's nodelets (full name -> Nodelet): a new plan keeps each on its manager's computer
    nodelets: Mapping[str, Nodelet] = field(default_factory=dict)
    #: the nodes the plan in force runs standalone (system.yaml names; plan.json ``standalone``)
    standalone: set[str] = field(default_factory=set)
    seq: int = 0
    applied: list[dict[str, Any]] = field(default_factory=list)
    _mtime: float = 0.0

    def tick(self, restarter: Restarter) -> None:
        path = self.folder / CONTROL_FILE
        try:
            mtime = path.stat().st_mtime
        except OSError:
            return
        if mtime == self._mtime:
            return
        self._mtime = mtime
        try:
            self._apply(restarter, read_json(path))
        except PerfrosError as exc:  # a bad control file is not a reason to stop the run
            warnings.warn(f"{path}: not applied: {exc}", PerfrosWarning, stacklevel=2)

    def _apply(self, restarter: Restarter, doc: Any) -> None:
        if not isinstance(doc, dict) or doc.get("format") != CONTROL_FORMAT or not isinstance(doc.get("seq"), int):
            raise PerfrosError(f"not a deploy control file ({CONTROL_FORMAT} with a whole seq)")
        if doc["seq"] <= self.seq:
            return
        entry: dict[str, Any] = {"seq": doc["seq"], "t": time.time(), "why": doc.get("why")}
        if doc.get("links") is not None:
            entry["links"] = self._links(doc["links"])
        pids: dict[str, int] = {}
        if doc.get("plan") is not None:
            pids = self._plan(restarter, str(doc["plan"]), entry)
        self.seq = doc["seq"]
        self.applied.append(entry)
        if self.on_applied is not None:
            self.on_applied(pids)

    def _links(self, raw: Any) -> list[dict[str, Any]]:
        """Re-shape the links the control file names, in place; what was set."""
        import math

        if self.network is None:
            raise PerfrosError("this run emulates no links")
        system = self.network.system
        if not isinstance(raw, list):
            raise PerfrosError("'links' must be a list of {between: [a, b], bandwidth_kBps: x}")
        done = []
        for item in raw:
            between = item.get("between") if isinstance(item, dict) else None
            rate = item.get("bandwidth_kBps") if isinstance(item, dict) else None
            index = next((i for i, link in enumerate(system.links)
                          if isinstance(between, list) and sorted(link.between) == sorted(map(str, between))), None)
            if index is None:
                raise PerfrosError(f"no link between {between!r} in this run")
            if isinstance(rate, bool) or not isinstance(rate, int | float) or not math.isfinite(rate) or rate <= 0:
                raise PerfrosError(f"link {between}: bandwidth_kBps must be a finite number > 0, got {rate!r}")
            try:
                self.network.set_link_rate(index, float(rate))
            except OSError as exc:
                raise PerfrosError(f"link {between}: not re-shaped: {exc}") from None
            done.append({"between": list(system.links[index].between), "bandwidth_kBps": float(rate)})
        return done

    def _plan(self, restarter: Restarter, plan_path: str, entry: dict[str, Any]) -> dict[str, int]:
        from perfros_bag.rosrun.cgroups import computer_cores
        from perfros_bag.sweep.deploy import plan_run
        from perfros_bag.sweep.nodelets import check_plan_membership, standalone_nodelets
        from perfros_bag.system.names import system_node_name
        from perfros_bag.system.planfile import load_plan

        plan: Plan = load_plan(plan_path)
        plan.require_feasible(plan_path, "apply")
        new_run = plan_run(plan, self.space, self.arg_defaults)
        new_where = {name: pn.computer for name, pn in plan.nodes.items()}
        dropped = sorted(set(self.where) - set(new_where))
        if dropped:  # each running node needs the new plan's computer (and value): refused, the old plan runs on
            raise PerfrosError(f"{plan_path}: node(s) {', '.join(dropped)} of the plan in force are not in it: "
                               "a new plan must place every node the deploy runs")
        alone = plan.standalone
        check_plan_membership(self.nodelets, {**self.where, **new_where}, plan_path, alone)
        alone_nodelets = frozenset(standalone_nodelets(self.nodelets, alone, plan_path))
        unknown = sorted({c for c in new_where.values() if c not in self.groups.dirs})
        if unknown:
            raise PerfrosError(f"computer(s) {', '.join(unknown)} are not emulated in this run")
        changed = changed_nodes(self.run, new_run, self.where, new_where, self.standalone, alone)
        ros = {system_node_name(n): n for n in restarter.watch.pids}
        pids: dict[str, int] = {}
        if self.on_restarting is not None and any(node in ros for node in changed):
            self.on_restarting([ros[node] for node in changed if node in ros])
        moved = [node for node in changed if node in ros]  # restarted together, waited for together
        new_pids = restarter.restart_many([(ros[node], new_run.args, new_run.params, new_where[node])
                                           for node in moved],
                                          standalone=alone_nodelets)
        for node in moved:
            pid = new_pids[ros[node]]
            procs = self.groups.procs_file(new_where[node])
            if procs is not None:
                procs.write_text(str(pid))
            pids[ros[node]] = pid
        cores = computer_cores(plan, self.units_per_core)
        self.groups.cores.update(cores)
        if self.cap and self.groups.capped:
            self.groups.apply()
        self.run, self.where, self.standalone = new_run, {**self.where, **new_where}, alone
        self.plan_path = plan_path
        entry.update({"plan": plan_path, "restarted": sorted(pids), "values": dict(new_run.values), "cores": cores})
        return pids
