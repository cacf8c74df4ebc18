"""run_distributed: in-process vs a real 2-process LocalCluster, worker deaths, bad input.

One LocalCluster (2 worker processes, 1 thread each) is started for the whole module
and reached through ``scheduler=`` like an external cluster would be.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cloudpickle
import pytest

from perfros_bag.characterisation import distributed as dist
from perfros_bag.characterisation.distributed import Outcome, run_distributed
from perfros_bag.errors import InputError, PerfrosError

ROOT = Path(__file__).resolve().parent.parent
# Workers import perfros_bag, but not this test module: ship its functions by value.
cloudpickle.register_pickle_by_value(sys.modules[__name__])


def square_or_fail(x: int) -> int:
    if x % 5 == 3:
        raise InputError(f"rec{x}.bag", "truncated chunk at byte 1234")
    return x * x


def slow_square(x: int) -> tuple[int, int]:
    time.sleep(0.25)
    return x * x, os.getpid()


def kill_own_worker_on_9(x: int) -> int:
    from distributed import get_worker

    get_worker()  # raises outside a worker: never kill the test process
    if x == 9:
        os.kill(os.getpid(), signal.SIGKILL)
    return -x


@pytest.fixture(scope="module")
def local_cluster() -> Iterator[Any]:
    import logging

    import dask
    from distributed import LocalCluster

    # worker-saturation 1.0 as run_distributed's own LocalCluster: a worker holds only the
    # task it runs, so a dying worker takes no queued task with it.
    with dask.config.set({"distributed.scheduler.worker-saturation": 1.0}):
        lc = LocalCluster(n_workers=2, processes=True, threads_per_worker=1,
                          dashboard_address=None, silence_logs=logging.ERROR)
    try:
        yield lc
    finally:
        lc.close()


@pytest.fixture
def cluster(local_cluster: Any) -> str:
    return str(local_cluster.scheduler_address)


def _summary(outcomes: list[Outcome[int]]) -> list[tuple[str, int | None, str | None]]:
    return [(o.label, o.value, None if o.error is None else str(o.error)) for o in outcomes]


def test_local_path_imports_no_dask() -> None:
    code = ("import sys; from perfros_bag.characterisation.distributed import run_distributed as r; "
            "out = r([1, -2], abs); assert [o.value for o in out] == [1, 2], out; "
            "bad = [m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')]; "
            "assert not bad, bad")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


def test_local_reports_errors_and_keeps_order() -> None:
    seen: list[str] = []
    out = run_distributed(range(10), square_or_fail, progress=lambda o: seen.append(o.label))
    assert seen == [str(i) for i in range(10)]
    assert [o.value for o in out] == [None if i % 5 == 3 else i * i for i in range(10)]
    assert [str(o.error) for o in out if not o.ok] == [
        "rec3.bag: truncated chunk at byte 1234", "rec8.bag: truncated chunk at byte 1234"]
    assert all(o.error.exit_code == 2 for o in out if o.error is not None)


def test_cluster_gives_same_outcomes_as_local(cluster: str) -> None:
    seen: list[str] = []
    local = run_distributed(range(12), square_or_fail)
    remote = run_distributed(range(12), square_or_fail, scheduler=cluster,
                             progress=lambda o: seen.append(o.label))
    assert _summary(remote) == _summary(local)
    assert sorted(seen, key=int) == [str(i) for i in range(12)]  # every task reported once


def test_worker_killed_mid_run_loses_nothing(cluster: str) -> None:
    from distributed import Client

    with Client(cluster) as client:
        pids = client.run(os.getpid)
    assert len(pids) == 2
    victim = sorted(pids.values())[0]
    done: list[Outcome[tuple[int, int]]] = []

    def on_done(outcome: Outcome[tuple[int, int]]) -> None:
        done.append(outcome)
        if len(done) == 2:  # both workers are busy with the queue: kill one of them
            os.kill(victim, signal.SIGKILL)

    out = run_distributed(range(16), slow_square, scheduler=cluster, progress=on_done)
    assert [o.value[0] if o.value else None for o in out] == [i * i for i in range(16)]
    worker_pids = {o.value[1] for o in out if o.value}
    assert os.getpid() not in worker_pids  # the work really ran in worker processes
    with pytest.raises(ProcessLookupError):
        os.kill(victim, 0)  # the victim is gone; its tasks were re-run elsewhere
    assert [o.value[1] for o in done[2:] if o.value].count(victim) == 0


def test_task_that_always_kills_its_worker_is_a_clear_error(local_cluster: Any) -> None:
    # Give a task up as soon as its worker died once (default: after 3 deaths), so the poison
    # task costs only two worker restarts (run_distributed resubmits it once).
    scheduler = local_cluster.scheduler
    allowed, scheduler.allowed_failures = scheduler.allowed_failures, 0
    try:
        out = run_distributed(range(10), kill_own_worker_on_9,
                              scheduler=local_cluster.scheduler_address)
    finally:
        scheduler.allowed_failures = allowed
    assert [o.value for o in out[:9]] == [-i for i in range(9)], [str(o.error) for o in out if o.error]
    bad = out[9]
    assert bad.value is None and bad.error is not None
    assert str(bad.error).startswith("9: the Dask worker running this task died")


def test_characterise_on_the_cluster_gives_the_same_csv(cluster: str, tmp_path: Path) -> None:
    # The CLI with --scheduler pointing at the module's 2-process LocalCluster. (--workers N,
    # where run_distributed starts its own LocalCluster, is the same code after start-up;
    # tests/test_characterise.py runs it with --workers 1, the benchmark with --workers 2.)
    from typer.testing import CliRunner

    from perfros_bag.cli import app
    from tests.bench.gen_corpus import FORMATS, default_topics, write_recording

    rec = tmp_path / "recs"
    rec.mkdir()
    for k, fmt in enumerate(FORMATS * 2):
        name = f"r{k}_{fmt}" + {"ros1": ".bag", "mcap": ".mcap"}.get(fmt, "")
        write_recording(rec / name, fmt, default_topics(0.01), 2.0 + k, chunk_bytes=4096, seed=k)
    good = (rec / "r0_ros1.bag").read_bytes()
    (rec / "r9_cut.bag").write_bytes(good[: len(good) // 2])  # a truncated bag: one error line

    def characterise(*extra: str) -> tuple[bytes, list[str]]:
        out = tmp_path / f"out{len(extra)}.csv"
        res = CliRunner().invoke(app, ["characterise", str(rec), "--out", str(out), *extra])
        assert res.exit_code == 1, res.stderr  # one bad recording: exit 1, the others written
        assert "Traceback" not in res.stderr
        errors = [line for line in res.stderr.splitlines() if line.startswith("error:")]
        head, *rows = out.read_bytes().splitlines(keepends=True)
        return head + b"".join(sorted(rows)), errors

    local_csv, local_errors = characterise()
    dask_csv, dask_errors = characterise("--scheduler", cluster)
    diff = [(a, b) for a, b in zip(local_csv.splitlines(), dask_csv.splitlines(), strict=False) if a != b]
    assert dask_csv == local_csv, (diff, dask_errors)
    assert dask_errors == local_errors and len(local_errors) == 1 and "r9_cut.bag" in local_errors[0]
    assert local_csv.count(b"\n") == 1 + 8 * 4  # header + 8 recordings x 4 topics


def test_bad_options_and_unreachable_scheduler(monkeypatch: pytest.MonkeyPatch) -> None:
    with pytest.raises(PerfrosError, match="both a Dask scheduler address and a number of local workers"):
        run_distributed([1], abs, scheduler="tcp://127.0.0.1:1", workers=2)
    with pytest.raises(PerfrosError, match="at least 1"):
        run_distributed([1], abs, workers=0)
    monkeypatch.setattr(dist, "CONNECT_TIMEOUT", "1s")
    with pytest.raises(PerfrosError, match="cannot connect to the Dask scheduler tcp://127.0.0.1:1"):
        run_distributed([1], abs, scheduler="tcp://127.0.0.1:1")


def test_fleet_splits_large_recordings_and_gives_the_local_rows(cluster: str, tmp_path: Path) -> None:
    from perfros_bag.characterisation.cluster import characterise_on_dask, plan_units
    from perfros_bag.characterisation.table import characterise, find_entries
    from tests.bench.gen_corpus import default_topics, write_recording

    for k, (name, fmt, comp, secs) in enumerate([
            ("big.bag", "ros1", "lz4", 8.0), ("big.mcap", "mcap", "zstd", 8.0),
            ("small.bag", "ros1", "none", 1.0), ("dir2", "rosbag2-sqlite3", "none", 8.0)]):
        write_recording(tmp_path / name, fmt, default_topics(0.02), secs, chunk_bytes=8000,
                        compression=comp, seed=k)
    # a CPU trace for the split bag: its rows carry CPU read on the client after the merge
    t0 = 1_700_000_000.0
    lines = ["# host=test", "# logical_cpus=2", "# interval_s=0.5", "time,pid,node,process,cpu_percent,rss_bytes"]
    lines += [f"{t0 + 0.5 * i:.1f},42,/camera_driver,camera,{20 + i % 5},1000" for i in range(16)]
    (tmp_path / "big.cpu.csv").write_text("\n".join(lines) + "\n")
    (tmp_path / "cut.mcap").write_bytes((tmp_path / "big.mcap").read_bytes()[:5000])
    entries, _ = find_entries(tmp_path)
    assert sorted(e.name for e in entries) == ["big.bag", "big.mcap", "cut.mcap", "dir2", "small.bag"]

    units, plans = plan_units(entries, split_bytes=300_000, part_bytes=30_000)
    split = {entries[i].name for i in plans}
    assert split == {"big.bag", "big.mcap"}  # small.bag is under split_bytes; cut.mcap has no index
    assert len(units) > len(entries) + 4

    local = characterise(entries)
    seen: list[str] = []
    remote = characterise_on_dask(entries, None, scheduler=cluster, split_bytes=300_000,
                                  part_bytes=30_000, progress=lambda o: seen.append(o.label))
    assert sorted(seen) == sorted(e.name for e in entries)  # once per recording, not per part
    rows = [r for o in remote if o.value for r in o.value]
    assert rows == local.rows
    assert any(r.cpu_units_mean for r in rows if r.recording == "big.bag")
    errors = {o.label: str(o.error) for o in remote if o.error is not None}
    assert errors == {f.recording: f.message for f in local.failures} and list(errors) == ["cut.mcap"]


def test_fleet_latency_on_dask_equals_the_local_latency(cluster: str, tmp_path: Path) -> None:
    """characterise --latency on Dask: split recordings' parts bring their stamps, merged
    before the percentiles; whole recordings read theirs on the worker: the local rows."""
    from perfros_bag.characterisation.cluster import characterise_on_dask, plan_units
    from perfros_bag.characterisation.table import characterise, find_entries
    from tests.contents_gen import sent_messages, write_mcap, write_ros1, write_rosbag2

    sent = sent_messages(600)
    write_ros1(tmp_path / "big.bag", sent, "lz4")
    write_mcap(tmp_path / "big.mcap", sent, big_endian_every=5)
    write_rosbag2(tmp_path / "dir2", sent)
    entries, _ = find_entries(tmp_path)
    _, plans = plan_units(entries, split_bytes=20_000, part_bytes=20_000)
    assert {entries[i].name for i in plans} == {"big.bag", "big.mcap"}
    local = characterise(entries, latency=True)
    remote = characterise_on_dask(entries, None, scheduler=cluster, split_bytes=20_000,
                                  part_bytes=20_000, latency=True)
    rows = [r for o in remote if o.value for r in o.value]
    assert rows == local.rows and not local.failures
    stamped = [r for r in rows if r.topic in ("/imu", "/detector/scored")]
    assert len(stamped) == 6 and all(r.latency_p95_s is not None for r in stamped)


class UnforeseenSettings(dict[str, Any]):
    """Settings whose lookup fails as a reader's unforeseen bug would (KeyError): shipped to
    the workers by value with this module, so the real characterise code fails there too."""

    def get(self, key: str, default: Any = None) -> Any:
        raise KeyError(f"unforeseen {key}")


def test_unforeseen_exception_reads_the_same_locally_and_on_dask(cluster: str, tmp_path: Path) -> None:
    from perfros_bag.characterisation.cluster import characterise_on_dask
    from perfros_bag.characterisation.manifest import RecordingEntry
    from perfros_bag.characterisation.table import characterise
    from tests.bench.gen_corpus import default_topics, write_recording

    for name, secs in (("good.bag", 1.0), ("odd.bag", 1.0), ("odd_big.bag", 8.0)):
        write_recording(tmp_path / name, "ros1", default_topics(0.02), secs, chunk_bytes=8000)
    entries = [RecordingEntry(tmp_path / "good.bag", "good.bag"),
               RecordingEntry(tmp_path / "odd.bag", "odd.bag", settings=UnforeseenSettings()),
               RecordingEntry(tmp_path / "odd_big.bag", "odd_big.bag", settings=UnforeseenSettings())]

    local = characterise(entries)
    expected = {f.recording: f.message for f in local.failures}
    assert expected == {n: f"{tmp_path / n}: cannot read: KeyError: 'unforeseen /camera_driver'"
                        for n in ("odd.bag", "odd_big.bag")}
    assert local.rows and {r.recording for r in local.rows} == {"good.bag"}

    remote = characterise(entries, scheduler=cluster)  # one task per recording
    assert {f.recording: f.message for f in remote.failures} == expected
    assert remote.rows == local.rows and remote.exit_code == local.exit_code == 1

    # odd_big.bag split into chunk-range tasks: the rows are built on the client after the merge
    split = characterise_on_dask(entries, None, scheduler=cluster, split_bytes=100_000,
                                 part_bytes=20_000)
    assert {o.label: str(o.error) for o in split if o.error is not None} == expected
