"""``watch --adapt``'s refit and re-solve, off the window loop: a child process.

A refit on the case study's characterisation took up to 79 s on a loaded machine; made on
the loop, no window came meanwhile. So the loop hands it to a child process
(:func:`start`): the watched plan, the live windows' rows, the alarms and the world go into
``replan-<k>/`` (``watched-plan.json``, ``windows.csv``, ``request.json``), and
a child runs :meth:`~perfros_bag.watch.adapt.Adapter.prepare` on it (its answer in
``result.json``). The child is started ahead (:func:`warm`: ``python -m
perfros_bag.watch.refit --standby PID``, its imports done while nothing drifts, its output in
``DIR/refit.log``) and handed the request's path on its stdin; one is warmed again after
each re-plan. Without a waiting one, ``python -m perfros_bag.watch.refit
replan-<k>/request.json`` starts there and then (its output in ``replan-<k>/refit.log``).
The loop goes on making windows; each of its quarter-second steps asks
:meth:`Pending.poll`, and when the child is done the loop applies the new plan
(:meth:`~perfros_bag.watch.adapt.Adapter.apply`: control.json, adapt.jsonl) at once.

The child runs in a session of its own (a terminal's Ctrl-C does not reach it): the watch
ends it (and a waiting one) on Ctrl-C, on an error and when the deploy or the master goes
away (:meth:`Pending.cancel`, :func:`end`); should the watch itself be killed outright, the child notices
that its parent changed and exits. A child process rather than a thread: it holds no lock
the loop needs (Python's GIL, the warnings filters), and it can be ended.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from perfros_bag.errors import PerfrosError, PerfrosWarning

if TYPE_CHECKING:
    from perfros_bag.characterisation.csvfile import Row
    from perfros_bag.system.plan import Plan
    from perfros_bag.watch.adapt import Adapter

REQUEST, RESULT, LOG = "request.json", "result.json", "refit.log"
REQUEST_FORMAT = "perfros-bag/watch-refit@1"


@dataclass
class Pending:
    """A re-plan whose refit runs in a child process."""

    adapter: Adapter
    window: int
    folder: Path
    proc: subprocess.Popen[bytes]
    started: float  # time.time() when it was asked for
    log: Path  # the child's output
    #: the running plan's measured Σ w·P in the windows that asked for it (``measured``,
    #: ``windows``), which the re-plan must not predict below (:func:`~perfros_bag.watch.adapt.worse_than_running`)
    running: dict[str, Any] | None = None

    def poll(self) -> bool:
        """Whether the child has ended."""
        return self.proc.poll() is not None

    def wait(self, timeout: float | None = None) -> None:
        self.proc.wait(timeout)

    def finish(self, stale: str | None = None) -> dict[str, Any] | None:
        """The ended child's re-plan, applied (control.json when attached to a deploy, and
        adapt.jsonl; only logged, as not sent, when ``stale`` says why); None with a warning
        when there is none."""
        from perfros_bag.fileio import read_json

        answer: Any = None
        if (self.folder / RESULT).is_file():
            try:
                answer = read_json(self.folder / RESULT)
            except PerfrosError:
                answer = None
        if not isinstance(answer, dict):
            answer = {"error": f"the refit process ended with code {self.proc.returncode} "
                               f"(its output: {self.log})"}
        for line in answer.get("warnings") or []:
            warnings.warn(f"--adapt: window {self.window}: {line}", PerfrosWarning, stacklevel=2)
        if answer.get("error") is not None or not isinstance(answer.get("entry"), dict):
            warnings.warn(f"--adapt: window {self.window}: no re-plan: {answer.get('error')}", PerfrosWarning,
                          stacklevel=2)
            return None
        running = {"running": self.running} if self.running is not None else {}
        return self.adapter.apply({**answer["entry"], "asked_t": self.started, **running}, stale=stale)

    def cancel(self) -> None:
        """End the child if it still runs (and reap it)."""
        end(self.proc)


def _command(adapter: Adapter) -> list[str]:
    return list(adapter.command or (sys.executable, "-m", "perfros_bag.watch.refit"))


def warm(adapter: Adapter) -> subprocess.Popen[bytes]:
    """A refit child started ahead of need (``--standby``): it imports what a refit and a
    re-solve use (numpy, scikit-learn, HiGHS, the fitting and solver modules: seconds on a
    loaded machine), then waits for one request's path on its stdin. Its output goes to
    ``DIR/refit.log``."""
    adapter.out.mkdir(parents=True, exist_ok=True)
    with (adapter.out / LOG).open("ab") as log:
        return subprocess.Popen([*_command(adapter), "--standby", str(os.getpid())], stdin=subprocess.PIPE,
                                stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def start(adapter: Adapter, plan: Plan, rows: list[Row], alarms: list[dict[str, Any]], k: int,
          world: dict[str, Any], standby: subprocess.Popen[bytes] | None = None,
          running: dict[str, Any] | None = None) -> Pending:
    """Start the refit and re-solve of window ``k``'s re-plan in a child process: ``standby``
    (:func:`warm`) when it still waits, else a new one. ``running``: the running plan's
    measure the re-plan is held against (:attr:`Pending.running`)."""
    from perfros_bag.characterisation.csvfile import write_characterisation
    from perfros_bag.fileio import atomic_write_json
    from perfros_bag.system.planfile import save_plan

    folder = adapter.out / f"replan-{k:05d}"
    folder.mkdir(parents=True, exist_ok=True)
    (folder / RESULT).unlink(missing_ok=True)
    save_plan(plan, folder / "watched-plan.json")
    if rows:
        write_characterisation(folder / "windows.csv", rows)
    fields = {key: (str(v) if isinstance(v, Path) else v) for key, v in asdict(adapter).items()}
    fields["command"] = None
    atomic_write_json(folder / REQUEST, {"format": REQUEST_FORMAT, "adapter": fields,
                                         "plan": str(folder / "watched-plan.json"),
                                         "rows": str(folder / "windows.csv") if rows else None,
                                         "alarms": alarms, "window": k, "world": world, "parent": os.getpid()})
    if standby is not None and standby.poll() is None and standby.stdin is not None:
        try:
            standby.stdin.write(f"{folder / REQUEST}\n".encode())
            standby.stdin.close()
            return Pending(adapter, k, folder, standby, time.time(), adapter.out / LOG, running)
        except OSError:  # it ended meanwhile: a new one
            end(standby)
    with (folder / LOG).open("wb") as log:
        proc = subprocess.Popen([*_command(adapter), str(folder / REQUEST)], stdin=subprocess.DEVNULL, stdout=log,
                                stderr=subprocess.STDOUT, start_new_session=True)
    return Pending(adapter, k, folder, proc, time.time(), folder / LOG, running)


def end(proc: subprocess.Popen[bytes]) -> None:
    """Terminate ``proc`` if it still runs (killed after 5 s) and reap it."""
    if proc.stdin is not None:
        try:
            proc.stdin.close()
        except OSError:
            pass
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def _orphaned(parent: int) -> None:
    """Exit as soon as the watch that started this child is gone (killed outright)."""
    while True:
        if os.getppid() != parent:
            os._exit(3)
        time.sleep(0.5)


def run(request_path: Path) -> dict[str, Any]:
    """The child's work: the request's :meth:`Adapter.prepare`, as ``result.json`` holds it."""
    from perfros_bag.characterisation.csvfile import read_characterisation
    from perfros_bag.fileio import read_json
    from perfros_bag.system.planfile import load_plan
    from perfros_bag.watch.adapt import Adapter

    req = read_json(request_path)
    if not isinstance(req, dict) or req.get("format") != REQUEST_FORMAT:
        return {"error": f"{request_path}: not a refit request ({REQUEST_FORMAT})"}
    a = req["adapter"]
    adapter = Adapter(Path(a["out"]), Path(a["plan_path"]), None if a["launch"] is None else Path(a["launch"]),
                      None if a["space"] is None else Path(a["space"]),
                      None if a["deployment"] is None else Path(a["deployment"]), int(a["sent"]))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", PerfrosWarning)
        try:
            rows = [] if req["rows"] is None else list(read_characterisation(req["rows"]).rows)
            entry = adapter.prepare(load_plan(req["plan"]), rows,
                                    list(req["alarms"]), int(req["window"]), dict(req["world"] or {}))
            answer: dict[str, Any] = {"entry": entry}
        except PerfrosError as exc:
            answer = {"error": str(exc)}
    answer["warnings"] = [str(w.message) for w in caught if issubclass(w.category, PerfrosWarning)]
    return answer


def _imports() -> None:
    """What a refit and a re-solve import, imported ahead (a standby child)."""
    import importlib

    for name in ("numpy", "sklearn.linear_model", "highspy", "perfros_bag.fitting.build", "perfros_bag.solver",
                 "perfros_bag.tune.loop", "perfros_bag.fitting.modelfile", "perfros_bag.characterisation.csvfile"):
        try:
            importlib.import_module(name)
        except ImportError:  # the refit says what is missing, if it needs it
            pass


def main(argv: list[str]) -> int:
    """``REQUEST``: make that re-plan; ``--standby PARENT``: import first, then read the
    request's path from stdin (none: the watch ended first, exit)."""
    from perfros_bag.fileio import atomic_write_json, read_json

    if argv[:1] == ["--standby"]:
        threading.Thread(target=_orphaned, args=(int(argv[1]),), daemon=True).start()
        _imports()
        line = sys.stdin.readline().strip()
        if not line:
            return 0
        request = Path(line)
    else:
        request = Path(argv[0])
        parent = read_json(request).get("parent")
        if isinstance(parent, int):
            threading.Thread(target=_orphaned, args=(parent,), daemon=True).start()
    atomic_write_json(request.parent / RESULT, run(request))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
