"""Shared test helpers: paths to the bundled fixtures and to ../shared/realbags."""

from __future__ import annotations

import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

# A suite started in the background of a non-interactive shell (``make test &``, nohup)
# inherits SIGINT ignored, and so would every process a test starts: the Ctrl-C tests would
# then wait for a run that never hears them. Put the default back; children get it on exec.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)

ROOT = Path(__file__).resolve().parent.parent
FIXTURES = ROOT / "fixtures"
# The real recordings are maintained outside the project, beside the checkout.
REALBAGS = Path(os.environ.get("PERFROS_REALBAGS", ROOT.parent / "shared" / "realbags"))


#: Test files that make real cgroups, namespaces or ROS processes without a ``ros``/``net`` mark
SERIAL_FILES = frozenset({"test_casestudy.py"})


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Under ``pytest -n 2 --dist loadgroup`` (``make test``) the tests that run real ROS nodes,
    cgroups or network namespaces share one worker, one at a time: two of them side by side on
    a 2-core machine would starve each other's nodes; the rest spread over both workers.
    ``tryfirst``: xdist reads the mark in its own hook of this name, which runs first otherwise
    (tests/test_test_groups.py proves the grouping holds)."""
    for item in items:
        if item.get_closest_marker("ros") or item.get_closest_marker("net") or item.path.name in SERIAL_FILES:
            item.add_marker(pytest.mark.xdist_group("ros"))


@pytest.fixture
def realbags() -> Path:
    if not REALBAGS.is_dir():
        raise RuntimeError(f"real recordings not found at {REALBAGS} (set PERFROS_REALBAGS)")
    return REALBAGS


def assert_same_stats(a: object, b: object) -> None:
    """Two RecordingStats are the same, every topic's times included."""
    import numpy as np

    from perfros_bag.ingest.stats import RecordingStats

    assert isinstance(a, RecordingStats) and isinstance(b, RecordingStats)
    assert (a.path, a.format, a.method) == (b.path, b.format, b.method)
    assert list(a.topics) == list(b.topics)
    for name, x in a.topics.items():
        y = b.topics[name]
        assert (x.topic, x.msgtype, x.messages, x.bytes, x.publishers) == \
               (y.topic, y.msgtype, y.messages, y.bytes, y.publishers), name
        assert x.times_ns.dtype == y.times_ns.dtype and np.array_equal(x.times_ns, y.times_ns), name
        assert (x.frequency_hz, x.median_rate_hz, x.p95_gap_s) == \
               (y.frequency_hz, y.median_rate_hz, y.p95_gap_s)


def communicate_or_stacks(proc: subprocess.Popen[Any], timeout: float) -> tuple[Any, Any]:
    """``proc.communicate(timeout)``; when ``proc`` (a ``perfros-bag`` process) has not ended by
    then, fail with where it waits: SIGUSR1 makes it print every thread's stack
    (perfros_bag/entry.py), then it is killed and the test fails with that stderr's end."""
    try:
        return proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        proc.kill()
        _, err = proc.communicate()
        text = err.decode(errors="replace") if isinstance(err, bytes) else str(err or "")
        pytest.fail(f"{proc.args!r} did not end within {timeout:g} s; its stderr ends:\n{text[-8000:]}")


def fake_control_run(tmp_path: Path, computers: tuple[str, ...], nodes: tuple[str, ...]) -> tuple[Any, Any, list[str]]:
    """What a deploy's :class:`~perfros_bag.sweep.control.Control` acts on, without ROS: a
    restarter whose ``restart_many`` records the ROS nodes it is asked to restart (in the
    returned list), and the computers' CPU groups as folders under ``tmp_path``."""
    from types import SimpleNamespace

    from perfros_bag.rosrun.cgroups import CpuGroups

    calls: list[str] = []
    restarter = SimpleNamespace(watch=SimpleNamespace(pids={f"/{n}": (1, 0.0) for n in nodes}),
                                restart_many=lambda batch, standalone=frozenset(): {b[0]: calls.append(b[0]) or 100
                                                                                    for b in batch})
    groups = CpuGroups("t", dict.fromkeys(computers, 1.0), root=tmp_path)
    for c in computers:
        (tmp_path / c).mkdir()
        groups.dirs[c] = tmp_path / c
    return restarter, groups, calls
