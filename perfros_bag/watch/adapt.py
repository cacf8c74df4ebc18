"""``watch --adapt``: when a drift persists, refit with the live windows, re-solve, write.

The plan's model (plan.json ``system``, a model.json) is refitted, as ``tune`` refits on a
deployment, on the characterisation it was fitted on (read as ``tune --base`` reads one:
:func:`perfros_bag.tune.loop.base_rows`) plus the live windows' rows (recordings
``watch-<k>``, the nodes at their planned values); the new model is solved with the same
problem, method and headroom (the plan's ``headroom: auto``, else the largest share of a
computer its ``margin`` kept) and the plan's budgets (they are in the model). Applying is
writing, never restarting: ``DIR/replan-<k>/`` gets ``characterisation.csv``,
``model.json``, ``plan.json``, ``changes.txt`` (one line per node whose value, computer or
``standalone`` mark changed) and, with the launch file and space.yaml, ``planned.launch`` (``export --launch
--space``). Every re-plan, its reason (the alarms' lines) and what changed is one line of
``DIR/adapt.jsonl``.

Attached to a deploy, the re-solve also takes the world as it is now (``world``, from
:func:`world_now`): the links at the rates they are shaped to (``live.json`` ``links``),
each computer's capacity less the CPU its cgroup spends beyond the planned nodes (another
process: ``foreign``; the new plan keeps the computer's own capacity, so its cap is not
lowered, and says what it left to the other process in ``reserved_cpu``), and the values
the deploy runs that differ from the plan watched (an operator's change: ``pinned``, kept
as they are, never undone by the re-plan).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import PerfrosError, PerfrosWarning

if TYPE_CHECKING:
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.system.plan import Plan
    from perfros_bag.system.types import System

ADAPT_LOG = "adapt.jsonl"


def plan_headroom(plan: Plan) -> float | str:
    """The headroom the plan was solved with: ``auto`` when it says so, else the largest
    share of a computer's capacity its ``margin`` keeps free (0 without margins)."""
    if plan.extra.get("headroom") == "auto":
        return "auto"
    shares = [c.margin / c.capacity for c in plan.computers.values() if c.margin and c.capacity]
    return min(0.99, max(shares)) if shares else 0.0


def changes(old: Plan, new: Plan) -> list[str]:
    """One line per node whose value, computer or ``standalone`` mark (plan.json) differs
    between two plans."""
    lines = []
    for name in sorted(set(old.nodes) | set(new.nodes)):
        a, b = old.nodes.get(name), new.nodes.get(name)
        if a is None or b is None:
            lines.append(f"{name}: {'added' if a is None else 'removed'}")
            continue
        what = []
        if a.value != b.value:
            what.append(f"{a.parameter or 'value'} {a.value} -> {b.value}")
        if a.computer != b.computer:
            what.append(f"computer {a.computer} -> {b.computer}")
        if a.standalone != b.standalone:  # the deploy restarts it in or out of its container
            what.append("in its container -> standalone" if b.standalone else "standalone -> in its container")
        if what:
            lines.append(f"{name}: {', '.join(what)}")
    return lines


def world_system(system: System, world: dict[str, Any]) -> System:
    """``system`` as the world is now: links at their rates in force, each computer's
    capacity less its ``foreign`` CPU (never below 0), pinned nodes at their one value."""
    links = {tuple(sorted(map(str, x["between"]))): float(x["bandwidth_kBps"]) for x in world.get("links") or []}
    foreign = world.get("foreign") or {}
    pinned = world.get("pinned") or {}
    new_links = tuple(replace(link, bandwidth_kBps=links.get(tuple(sorted(link.between)), link.bandwidth_kBps))
                      for link in system.links)
    computers = tuple(c if c.capacity is None or not foreign.get(c.name)
                      else replace(c, capacity=max(0.0, c.capacity - float(foreign[c.name])))
                      for c in system.computers)
    nodes = []
    for n in system.nodes:
        value = pinned.get(n.name)
        if value is not None and n.settings:
            keep = min(n.settings, key=lambda st: abs((st.value if st.value is not None else math.inf) - value))
            n = replace(n, settings=(keep,), curve=None)
        nodes.append(n)
    return replace(system, links=new_links, computers=computers, nodes=tuple(nodes))


def worse_than_running(entry: dict[str, Any]) -> str | None:
    """Why a re-plan must not replace the running plan: it predicts a lower Σ w·P
    (``predicted_after``) than the running plan measured in the windows that raised its
    alarms (``running``: ``measured``, ``windows``). Adapting never makes things worse
    (issue 30): the running plan is kept, the windows go on judging it. None when the
    re-plan may go, or when there is nothing to compare (no measure: a window blind on a
    node, or running an operator's values that no plan in force holds)."""
    running, after = entry.get("running"), entry.get("predicted_after")
    if not isinstance(running, dict) or running.get("measured") is None or after is None:
        return None
    measured = float(running["measured"])
    if after >= measured:
        return None
    ks = running.get("windows") or []
    where = f"window(s) {ks[0]}-{ks[-1]}" if len(ks) > 1 else f"window {ks[0]}" if ks else "its last windows"
    return (f"it predicts Σ w·P {after:.4g}, below the {measured:.4g} the running plan measured in {where}: "
            "the running plan is kept")


@dataclass
class Adapter:
    out: Path
    plan_path: Path
    launch: Path | None = None
    space: Path | None = None
    deployment: Path | None = None  # a deploy in progress: the new plan goes to its control.json
    sent: int = 0  # control.json's last sequence number
    #: the refit child's command, before its request file (None: this Python, ``-m perfros_bag.watch.refit``)
    command: tuple[str, ...] | None = None

    def _model(self, plan: Plan) -> Path:
        if not plan.system:
            raise PerfrosError(f"{self.plan_path}: names no model.json (plan.json \"system\"): nothing to refit")
        raw = Path(plan.system)
        for cand in ([raw] if raw.is_absolute() else [self.plan_path.parent / raw, raw]):
            if cand.is_file():
                return cand
        raise PerfrosError(f"{self.plan_path}: its model {plan.system} was not found")

    def replan(self, plan: Plan, rows: list[Row], alarms: list[dict[str, Any]], k: int,
               world: dict[str, Any] | None = None) -> dict[str, Any] | None:
        """Refit, re-solve, write and apply, here and now (:meth:`prepare` then :meth:`apply`):
        the log entry (also appended to ``adapt.jsonl``), or None with a warning when it
        cannot (no model, or the new model has no plan). The watch loop does not call this:
        it runs :meth:`prepare` in a child process (:func:`perfros_bag.watch.refit.start`)."""
        try:
            return self.apply(self.prepare(plan, rows, alarms, k, world or {}))
        except PerfrosError as exc:
            warnings.warn(f"--adapt: window {k}: no re-plan: {exc}", PerfrosWarning, stacklevel=2)
            return None

    def prepare(self, plan: Plan, rows: list[Row], alarms: list[dict[str, Any]], k: int,
                world: dict[str, Any]) -> dict[str, Any]:
        """The heavy half: refit, re-solve and write ``replan-<k>/``; the log entry without
        ``applied`` (nothing is sent, nothing logged yet)."""
        import time

        from perfros_bag.characterisation.csvfile import write_characterisation
        from perfros_bag.fileio import atomic_write_text
        from perfros_bag.fitting.build import build_model
        from perfros_bag.fitting.modelfile import read_model, write_model
        from perfros_bag.solver import solve
        from perfros_bag.system.planfile import save_plan
        from perfros_bag.tune.loop import base_rows, load_model

        started = time.monotonic()
        model_path = self._model(plan)
        base = Path(read_model(model_path).characterisation)
        if not base.is_absolute() and not base.is_file():
            base = model_path.parent / base
        folder = self.out / f"replan-{k:05d}"
        folder.mkdir(parents=True, exist_ok=True)
        csv_path, new_model, new_plan_path = (folder / "characterisation.csv", folder / "model.json",
                                              folder / "plan.json")
        write_characterisation(csv_path, [*base_rows(base), *rows])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PerfrosWarning)
            write_model(new_model, build_model(model_path, csv_path).document)
            headroom = plan_headroom(plan)
            new = solve(world_system(load_model(new_model), world), plan.problem, str(plan.method),
                        headroom=headroom)
        new.require_feasible(new_model, "apply")
        reserved = {c: round(x, 3) for c, x in (world.get("foreign") or {}).items()
                    if x > 0 and c in new.computers and new.computers[c].capacity is not None}
        for c, x in reserved.items():  # the cap stays the computer's: the other process is in it
            pc = new.computers[c]
            new.computers[c] = replace(pc, capacity=(pc.capacity or 0.0) + x)
        if reserved:
            new.extra["reserved_cpu"] = reserved
        save_plan(new, new_plan_path)
        changed = changes(plan, new)
        atomic_write_text(folder / "changes.txt", "".join(f"{line}\n" for line in changed) or "no change\n")
        launch = None
        if self.launch is not None and self.space is not None:
            from perfros_bag.export.planned import export_planned

            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PerfrosWarning)
                export_planned(new_plan_path, self.launch, self.space, folder / "planned.launch")
            launch = str(folder / "planned.launch")
        return {"window": k, "why": [a["line"] for a in alarms], "plan": str(new_plan_path),
                "launch": launch, "objective_before": plan.objective, "objective_after": new.objective,
                "predicted_after": new.predicted_performance,
                "headroom": headroom, "changes": changed, "refit_s": round(time.monotonic() - started, 2),
                **({"world": world} if world else {})}

    def apply(self, entry: dict[str, Any], stale: str | None = None) -> dict[str, Any]:
        """Send a prepared re-plan to the deploy (when attached to one that still runs and the
        plan changes something; never when ``stale`` says why not) and append it to
        ``adapt.jsonl``; the completed entry."""
        import time

        from perfros_bag.fileio import atomic_write_text, json_text

        if stale is None:
            stale = worse_than_running(entry)
        applied = "written (nothing restarted)" if stale is None else f"not sent: {stale}"
        sent = False
        if self.deployment is not None and entry["changes"] and stale is None:
            from perfros_bag.errors import InputError
            from perfros_bag.sweep.control import control_seq, write_control
            from perfros_bag.sweep.livestate import read_live

            try:
                read_live(self.deployment)
            except InputError:
                applied = "written (nothing restarted: the deploy had ended)"
            else:
                self.sent = max(self.sent, control_seq(self.deployment)) + 1  # after an operator's own entries
                write_control(self.deployment, self.sent, entry["plan"], list(entry["why"]))
                sent = True
                applied = (f"sent to the deploy ({self.deployment / 'control.json'} seq {self.sent}): it restarts "
                           "the nodes whose value, computer or standalone mark changed")
        # ``applied`` says it for a reader; ``sent`` (control.json written) and ``held_back``
        # (why it was not sent, or None) say it for a program
        done = {**entry, "t": time.time(), "applied": applied, "sent": sent, "held_back": stale}
        log = self.out / ADAPT_LOG
        previous = log.read_text(encoding="utf-8") if log.exists() else ""
        atomic_write_text(log, previous + json_text(done, indent=None) + "\n")
        return done
