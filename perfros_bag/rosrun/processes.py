"""The processes of one run: started in their own process groups, tagged, stopped for sure.

Every process carries ``PERFROS_CASESTUDY_RUN=<run id>`` in its environment (inherited by
whatever it starts), so :func:`leftover_processes` can prove that nothing outlived a run
and :func:`kill_stale` can end what did. :meth:`Processes.stop` sends SIGINT to each
process group, then SIGTERM, then SIGKILL; :meth:`Processes.kill_leftovers` kills every
remembered descendant (roscore's rosmaster and roslaunch's nodes live in groups of their
own). :func:`sigterm_as_interrupt` routes SIGTERM/SIGHUP through the Ctrl-C cleanup path.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from types import FrameType
from typing import IO

from perfros_bag.errors import PerfrosError

#: The environment variable that tags every process of a run with the run's id.
RUN_ENV = "PERFROS_CASESTUDY_RUN"


@dataclass
class Started:
    name: str
    popen: subprocess.Popen[bytes]
    log: IO[bytes]


@dataclass
class Processes:
    """The processes of one run, each in its own session/process group."""

    run_id: str
    env: dict[str, str]
    started: list[Started] = field(default_factory=list)
    seen: dict[int, float] = field(default_factory=dict)  # pid -> create_time of every descendant

    def start(self, name: str, argv: list[str], log_path: Path, cwd: Path | None = None) -> Started:
        log = log_path.open("wb")
        try:
            popen = subprocess.Popen(argv, stdin=subprocess.DEVNULL, stdout=log, stderr=subprocess.STDOUT,
                                     env=self.env, cwd=cwd, start_new_session=True)
        except OSError as exc:
            log.close()
            raise PerfrosError(f"cannot start {name} ({argv[0]}): {exc.strerror or exc}") from None
        st = Started(name, popen, log)
        self.started.append(st)
        self.remember()
        return st

    def remember(self) -> None:
        """Note every current descendant (roscore's rosmaster/rosout live in other groups)."""
        import psutil

        for st in self.started:
            try:
                proc = psutil.Process(st.popen.pid)
                family = [proc, *proc.children(recursive=True)]
            except psutil.Error:
                continue
            for p in family:
                with contextlib.suppress(psutil.Error):
                    self.seen[p.pid] = p.create_time()

    def stop(self, names: list[str] | None = None, timeout: float = 8.0) -> None:
        """SIGINT the groups (of ``names``, or all, in reverse start order), then escalate."""
        self.remember()
        todo = [st for st in reversed(self.started) if names is None or st.name in names]
        for st in todo:
            signal_group(st.popen, signal.SIGINT)
        deadline = time.monotonic() + timeout
        for sig, wait in ((signal.SIGTERM, 3.0), (signal.SIGKILL, 3.0)):
            for st in todo:
                with contextlib.suppress(subprocess.TimeoutExpired):
                    st.popen.wait(max(0.0, deadline - time.monotonic()))
            still = [st for st in todo if st.popen.poll() is None]
            if not still:
                break
            for st in still:
                signal_group(st.popen, sig)
            deadline = time.monotonic() + wait
        for st in todo:
            with contextlib.suppress(subprocess.TimeoutExpired):
                st.popen.wait(1.0)
            st.log.close()

    def kill_leftovers(self) -> list[int]:
        """SIGKILL every remembered descendant still alive (same pid and start time)."""
        import psutil

        killed = []
        for pid, created in list(self.seen.items()):
            try:
                p = psutil.Process(pid)
                if abs(p.create_time() - created) > 0.01:
                    continue
                p.kill()
                killed.append(pid)
            except psutil.Error:
                continue
        for pid in killed:
            with contextlib.suppress(psutil.Error):
                psutil.Process(pid).wait(2.0)
        return killed


def signal_group(popen: subprocess.Popen[bytes], sig: int) -> None:
    """Send ``sig`` to the process group led by ``popen`` (or to the process alone)."""
    if popen.poll() is not None:
        return
    try:
        os.killpg(popen.pid, sig)
    except (ProcessLookupError, PermissionError):
        with contextlib.suppress(OSError):
            popen.send_signal(sig)


def leftover_processes(run_id: str | None = None) -> list[int]:
    """PIDs of live processes started by a run (of ``run_id``, or any)."""
    import psutil

    found = []
    for p in psutil.process_iter(["pid"]):
        try:
            env = p.environ()
        except (psutil.Error, OSError):
            continue
        tag = env.get(RUN_ENV)
        if tag is not None and (run_id is None or tag == run_id) and p.status() != psutil.STATUS_ZOMBIE:
            found.append(p.pid)
    return found


def kill_stale(run_id: str | None = None) -> list[int]:
    """SIGKILL every live process of a run (of ``run_id``, or any); returns their PIDs."""
    import psutil

    pids = leftover_processes(run_id)
    for pid in pids:
        with contextlib.suppress(psutil.Error):
            psutil.Process(pid).kill()
    for pid in pids:
        with contextlib.suppress(psutil.Error):
            psutil.Process(pid).wait(2.0)
    return pids


@contextlib.contextmanager
def sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM/SIGHUP raise KeyboardInterrupt, so they take the same cleanup path as Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    old = {s: signal.signal(s, handler) for s in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def wait_for(what: str, check: Callable[[], bool], timeout: float, alive: Callable[[], str | None]) -> None:
    """Poll ``check`` until true; :class:`PerfrosError` when ``alive`` names a process that
    exited meanwhile, or after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while not check():
        dead = alive()
        if dead:
            raise PerfrosError(f"{dead} exited while waiting for {what}")
        if time.monotonic() > deadline:
            raise PerfrosError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.2)


def ros_env(run_id: str, ros_home: Path) -> dict[str, str]:
    """The environment of a run's ROS processes: Debian's python3 and tools (this
    interpreter's venv taken off ``PATH``), ROS on loopback only, logs under ``ros_home``,
    and the run tag."""
    env = dict(os.environ)
    for k in ("PYTHONPATH", "PYTHONHOME", "VIRTUAL_ENV", "ROS_NAMESPACE"):
        env.pop(k, None)
    env["PATH"] = ":".join(p for p in env.get("PATH", "").split(":")
                           if p and not p.startswith(str(Path(sys.prefix)))) or "/usr/bin:/bin"
    env.update({"ROS_IP": "127.0.0.1", "ROS_HOME": str(ros_home),
                "ROS_LOG_DIR": str(ros_home / "log"), RUN_ENV: run_id, "PYTHONUNBUFFERED": "1"})
    return env
