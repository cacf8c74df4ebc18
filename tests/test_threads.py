"""Busy threads (issue 29 item 5): measured by ``record-cpu`` (the CPU trace's optional trailing
``threads`` column), read back by old and new readers, carried through characterisation and
``fit`` into the model's system part, and read from system.yaml (node or setting ``threads``)."""

from __future__ import annotations

import json
import math
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path
from typing import Any

import numpy as np
import psutil
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from perfros_bag.cpu import trace as cputrace
from perfros_bag.cpu.record import busy_threads
from perfros_bag.errors import InputError
from perfros_bag.system.systemfile import parse_system

ROOT = Path(__file__).resolve().parent.parent
BIN = ROOT / ".venv" / "bin" / "perfros-bag"
META = "# host=h\n# logical_cpus=2\n# interval_s=0.5\n"
OLD = META + "time,pid,node,process,cpu_percent,rss_bytes\n"
NEW = META + "time,pid,node,process,cpu_percent,rss_bytes,threads\n"


@settings(max_examples=200, deadline=None)
@given(ticks=st.lists(st.integers(0, 1000), min_size=1, max_size=12),
       start=st.lists(st.integers(0, 10_000), min_size=12, max_size=12))
def test_busy_threads_is_the_inverse_simpson_count_of_cpu_seconds(ticks: list[int], start: list[int]) -> None:
    """Against the formula written out (CPU seconds in clock ticks of 10 ms, as the kernel
    counts them): n equally busy threads give n, one busy beside idle ones 1, an idle
    process 0; a thread born in the interval counts all its seconds."""
    used = [t / 100 for t in ticks]
    before = {k: start[k] / 100 for k in range(len(used)) if k % 3}  # every third thread is new
    after = {k: (start[k] + t) / 100 if k % 3 else t / 100 for k, t in enumerate(ticks)}
    total, squares = sum(used), sum(u * u for u in used)
    want = total * total / squares if squares > 0 else 0.0
    assert busy_threads(before, after) == pytest.approx(want, rel=1e-6, abs=1e-9)
    assert 0.0 <= busy_threads(before, after) <= len(used) + 1e-9


def test_busy_threads_by_hand() -> None:
    assert busy_threads({}, {1: 0.5, 2: 0.5}) == pytest.approx(2.0)
    assert busy_threads({1: 1.0, 2: 3.0, 3: 0.0}, {1: 1.4, 2: 3.0, 3: 0.0}) == pytest.approx(1.0)
    assert busy_threads({1: 1.0}, {1: 1.0}) == 0.0
    assert busy_threads({}, {1: 0.3, 2: 0.1}) == pytest.approx(0.16 / 0.1)  # (0.4)^2 / (0.09 + 0.01)


def test_old_traces_read_without_threads_and_new_ones_with(tmp_path: Path) -> None:
    old = cputrace.parse_cpu_trace(OLD + "1.0,7,a,a,50,10\n2.0,7,a,a,30,10\n", "old.cpu.csv")
    assert not cputrace.has_threads(old) and np.isnan(old.threads).all() and len(old.threads) == 2
    assert cputrace.node_cpu(old, 100.0)["a"].threads is None
    text = NEW + "1.0,7,a,a,50,10,1.5\n1.0,8,a,h,10,10,0.5\n2.0,7,a,a,30,10,0\n3.0,9,b,b,20,10,\n"
    for fast in (True, False):
        tr = cputrace.parse_cpu_trace(text, "new.cpu.csv", fast=fast)
        assert cputrace.has_threads(tr)
        assert tr.threads[:3].tolist() == [1.5, 0.5, 0.0] and math.isnan(tr.threads[3])
        got = cputrace.node_cpu(tr, 100.0)
        # a's processes summed per sample: 2.0 at t=1, 0 at t=2 (idle: not counted) -> 2.0
        assert got["a"].threads == pytest.approx(2.0) and got["b"].threads is None
    # a reader of the six columns only (the contract before the column): the first six fields
    import csv
    import io

    rows = list(csv.reader(io.StringIO(text.split("threads\n", 1)[1])))
    assert [r[:6] for r in rows][0] == ["1.0", "7", "a", "a", "50", "10"]
    # written back with the column, and without it when asked for the six
    path = tmp_path / "w.cpu.csv"
    cputrace.write_cpu_trace(path, [(1.0, 7, "a", "a", 50.0, 10, 1.25), (1.0, 8, "b", "b", 5.0, 10, None)],
                    host="h", logical_cpus=2, interval_s=0.5, threads=True)
    back = cputrace.read_cpu_trace(path)
    assert back.threads[0] == 1.25 and math.isnan(back.threads[1])
    cputrace.write_cpu_trace(path, [(1.0, 7, "a", "a", 50.0, 10, 1.25)], host="h", logical_cpus=2, interval_s=0.5)
    assert "threads" not in path.read_text() and not cputrace.has_threads(cputrace.read_cpu_trace(path))


@pytest.mark.parametrize("cell, needle", [("-1", "threads must be >= 0"), ("x", "threads 'x' is not a number"),
                                          ("inf", "not a finite number")])
def test_bad_threads_cell_names_the_line(cell: str, needle: str) -> None:
    with pytest.raises(InputError, match=needle) as exc:
        cputrace.parse_cpu_trace(NEW + "1.0,7,a,a,50,10,1\n" + f"2.0,7,a,a,50,10,{cell}\n", "bad.cpu.csv")
    assert "line 6" in str(exc.value) and str(exc.value).startswith("bad.cpu.csv: ")


@settings(max_examples=60, deadline=None)
@given(rows=st.lists(st.tuples(st.floats(0, 2e9, allow_nan=False), st.integers(0, 2**40),
                               st.sampled_from(["a", "b"]), st.floats(0, 1e4, allow_nan=False),
                               st.floats(0, 64, allow_nan=False)), max_size=30))
def test_fast_and_careful_parsers_agree_on_threads(rows: list[tuple[float, int, str, float, float]]) -> None:
    text = NEW + "".join(f"{t!r},{p},{n},x,{c!r},1,{k!r}\n" for t, p, n, c, k in rows)
    fast, slow = cputrace.parse_cpu_trace(text, fast=True), cputrace.parse_cpu_trace(text, fast=False)
    assert fast.threads.tolist() == slow.threads.tolist() == [r[4] for r in rows]


HASHER = """
import hashlib, sys, threading, time
busy, seconds = int(sys.argv[1]), float(sys.argv[2])
data = bytes(1 << 20)
end = time.monotonic() + seconds
def work():
    while time.monotonic() < end:
        hashlib.sha256(data).digest()  # releases the GIL: the threads run in parallel
def idle():
    while time.monotonic() < end:
        time.sleep(0.05)
threads = [threading.Thread(target=work) for _ in range(busy)] + [threading.Thread(target=idle) for _ in range(3)]
for t in threads:
    t.start()
for t in threads:
    t.join()
"""


@pytest.mark.parametrize("busy", [1, 2])
def test_record_cpu_counts_busy_threads_of_a_real_process(tmp_path: Path, busy: int) -> None:
    """A process with ``busy`` hashing threads beside 3 sleeping ones: the recorder's
    ``threads`` column against the same formula on psutil's own per-thread times of the
    process over the recording (the reference), and against the thread count psutil gives
    (5 or 6 with the main thread): what CFS shares among is the busy ones."""
    marker = f"threads_{uuid.uuid4().hex[:8]}"
    script = tmp_path / "hasher.py"
    script.write_text(HASHER)
    out = tmp_path / "run.cpu.csv"
    from tests.test_cputrace import _wait_for_recording

    rec = subprocess.Popen([str(BIN), "record-cpu", "--match", marker, "--interval", "0.5", "--out", str(out),
                            "--quiet", "--no-speed"], stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    _wait_for_recording(out, rec)
    child = subprocess.Popen([sys.executable, str(script), str(busy), "5.0", marker])
    try:
        proc = psutil.Process(child.pid)
        time.sleep(0.8)
        first = {t.id: t.user_time + t.system_time for t in proc.threads()}
        time.sleep(3.5)
        last = {t.id: t.user_time + t.system_time for t in proc.threads()}
        assert proc.num_threads() == busy + 4
        assert child.wait(30) == 0
        rec.send_signal(signal.SIGINT)
    finally:
        child.kill()
        _, stderr = rec.communicate(timeout=60)
    assert rec.returncode == 0, stderr
    used = [last[k] - first.get(k, 0.0) for k in last]
    reference = sum(used) ** 2 / sum(u * u for u in used)
    tr = cputrace.read_cpu_trace(out)
    mine = (tr.pid == child.pid) & (tr.cpu_percent > 0)
    assert mine.sum() >= 3
    measured = float(np.median(tr.threads[mine]))
    assert abs(measured - reference) <= 0.35, (measured, reference)
    assert abs(measured - busy) <= 0.35, (measured, busy)


def _system(threads_node: Any = None, threads_setting: Any = None) -> dict[str, Any]:
    node: dict[str, Any] = {"name": "det", "weight": 1.0, "parameter": {"name": "scale"}, "topics": ["/det/out"],
                            "settings": [{"value": 1.0, "cpu": 10.0, "performance": 50},
                                         {"value": 2.0, "cpu": 20.0, "performance": 100}]}
    if threads_node is not None:
        node["threads"] = threads_node
    if threads_setting is not None:
        node["settings"][1]["threads"] = threads_setting
    return {"computers": [{"name": "robot", "kind": "robot", "capacity": 100}], "nodes": [node]}


def test_system_threads_on_node_and_setting() -> None:
    det = parse_system(_system(2.5, 1.5), "s.yaml").node["det"]
    assert det.threads_at(1.0) == 2.5 and det.threads_at(2.0) == 1.5 and det.threads_at(None) == 2.5
    plain = parse_system(_system(), "s.yaml").node["det"]
    assert plain.threads_at(2.0) == 1.0


@pytest.mark.parametrize("node, setting", [(0.5, None), ("two", None), (None, 0), (None, float("nan"))])
def test_bad_threads_in_system_is_one_line(tmp_path: Path, node: Any, setting: Any) -> None:
    path = tmp_path / "s.yaml"
    path.write_text(yaml.safe_dump(_system(node, setting)))
    r = subprocess.run([str(BIN), "solve", str(path), "--out", str(tmp_path / "p.json")], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode == 2 and "threads" in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "Traceback" not in r.stderr and not (tmp_path / "p.json").exists()


def test_fit_writes_each_nodes_mean_busy_threads(tmp_path: Path) -> None:
    """Characterisation rows with ``threads`` (two topics of one recording: counted once):
    the model's system part gets the mean over the recordings, rounded to 0.01, at least 1;
    a node without the column gets none."""
    from perfros_bag.characterisation.csvfile import (
        Row,
        read_characterisation,
        write_characterisation,
    )
    from perfros_bag.fitting.build import build_model
    from perfros_bag.fitting.modelfile import write_model

    system = _system()
    system["nodes"].append({"name": "cam", "weight": 1.0, "topics": ["/cam"],
                            "settings": [{"cpu": 5.0, "performance": 100}]})
    rows = []
    for rec, value, cpu, threads in (("r1", 1.0, 10.0, 1.8), ("r2", 2.0, 21.0, 2.31), ("r3", 2.0, 19.0, 2.2)):
        for topic in ("/det/out", "/det/debug"):
            rows.append(Row(rec, "det", "scale", value, topic, "x/Y", 100, 10.0, 10.0, 1.0, cpu, cpu, 20,
                            threads=threads))
        rows.append(Row(rec, "cam", None, None, "/cam", "x/Y", 100, 10.0, 10.0, 1.0, 5.0, 5.0, 20))
    (tmp_path / "system.yaml").write_text(yaml.safe_dump(system))
    write_characterisation(tmp_path / "c.csv", rows)
    assert read_characterisation(tmp_path / "c.csv").rows[0].threads == 1.8  # the optional column round-trips
    with pytest.warns():
        result = build_model(tmp_path / "system.yaml", tmp_path / "c.csv")
    write_model(tmp_path / "model.json", result.document)
    nodes = {n["name"]: n for n in json.loads((tmp_path / "model.json").read_text())["system"]["nodes"]}
    assert nodes["det"]["threads"] == round((1.8 + 2.31 + 2.2) / 3, 2)
    assert "threads" not in nodes["cam"]
    assert result.system.node["det"].threads_at(2.0) == pytest.approx(2.1)
