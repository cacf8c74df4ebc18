"""``watch --deployment`` on a real ``deploy`` of the README example (fixtures/app: Debian's
image_publisher camera on a robot, opencv_apps' hough_circles detector on a server, joined
by a shaped link in network namespaces): the JSON windows while it runs, a new plan applied
through control.json (the camera alone restarted, at its new rate), the camera killed and
named by an alarm within 2 windows, and nothing left afterwards.

Independent checks: the camera's rate in the windows against its launch argument (10 Hz);
the link's load against the frames counted and the image's size (320 x 240 RGB); the
chain's latency from its last topic's stamps, as many as that topic's publisher counted; the killed
node's PID from the deploy's own live.json, killed here; afterwards no process
with the run's tag, no cgroup, no namespace of the run, and the watch itself exited.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.rosrun.cgroups import leftover_groups
from perfros_bag.rosrun.network import leftover_namespaces
from perfros_bag.rosrun.processes import leftover_processes
from tests.test_sweep_e2e import APP, BIN, _cli, _require_ros, _space

pytestmark = [pytest.mark.ros, pytest.mark.net]


def start_deploy(plan: Path, space: Path, system: Path, run: Path, **popen: Any) -> subprocess.Popen[str]:
    """``deploy`` of fixtures/app for 60 s into ``run``, in the background."""
    return subprocess.Popen([str(BIN), "deploy", str(plan), str(APP), "--space", str(space), "--out", str(run),
                             "--duration", "60", "--system", str(system)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, **popen)


def await_live(run: Path, deploy: subprocess.Popen[str]) -> dict[str, Any]:
    """The deploy's live.json, once its nodes run (at most 120 s)."""
    deadline = time.monotonic() + 120
    while not (run / "live.json").exists() and deploy.poll() is None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert (run / "live.json").exists(), deploy.stderr.read() if deploy.stderr else ""
    live: dict[str, Any] = json.loads((run / "live.json").read_text())
    return live


def stop_all(*procs: subprocess.Popen[str] | None) -> None:
    """Ctrl-C each process still running (a test that failed half-way)."""
    for p in procs:
        if p is not None and p.poll() is None:
            p.send_signal(signal.SIGINT)
            p.wait(timeout=60)


def nothing_left(run: Path, run_id: str | None) -> None:
    """The deploy's live.json gone, and no process, namespace or cgroup of its run."""
    assert not (run / "live.json").exists()
    assert run_id is not None
    assert leftover_processes(run_id) == []
    assert leftover_namespaces(f"d{run_id}") == []
    assert leftover_groups(run_id=run_id) == []


def psutil_alive(pid: int) -> bool:
    import psutil

    return psutil.pid_exists(pid) and psutil.Process(pid).status() != psutil.STATUS_ZOMBIE

SYSTEM = {
    "computers": [{"name": "robot1", "kind": "robot", "capacity": 100},
                  {"name": "server", "kind": "server", "capacity": 100}],
    "links": [{"between": ["robot1", "server"], "bandwidth_kBps": 6000}],
    "edges": [{"from": "camera", "to": "detector", "topic": "/camera/image_raw"}],
    "nodes": [
        {"name": "camera", "weight": 1, "residence": ["robot1"], "parameter": {"name": "publish_rate", "unit": "Hz"},
         "topics": ["/camera/image_raw"],
         "settings": [{"value": 10, "cpu": 10, "performance": 100, "frequency_hz": 10, "bandwidth_kBps": 2300}]},
        {"name": "detector", "weight": 1, "residence": ["server"], "parameter": {"name": "canny_threshold"},
         "topics": ["/detector/circles"],
         "settings": [{"value": 200, "cpu": 20, "performance": 100, "frequency_hz": 10, "bandwidth_kBps": 1}]},
    ],
}


def test_watch_attaches_to_a_deploy_and_names_a_killed_node(tmp_path: Path) -> None:
    _require_ros()
    system = tmp_path / "system.yaml"
    system.write_text(yaml.safe_dump(SYSTEM, sort_keys=False))
    step = _cli("solve", str(system), "--problem", "1", "--method", "exact", "--out", str(tmp_path / "plan.json"))
    assert step.returncode == 0, step.stderr
    doc = json.loads((tmp_path / "plan.json").read_text())  # a predicted chain (as solve writes it for budgets)
    doc["chains"] = [{"name": "vision", "topics": ["/camera/image_raw", "/detector/circles"],
                      "predicted_ms": {"p50": 1000.0, "p95": 1000.0}}]
    (tmp_path / "plan.json").write_text(json.dumps(doc))
    space = _space(tmp_path / "space.yaml", duration_s=4, settle_s=1, design="grid",
                   vary=[{"node": "camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate",
                          "values": [10]},
                         {"node": "detector", "parameter": {"name": "canny_threshold"}, "arg": "canny_threshold",
                          "values": [200]}])
    run = tmp_path / "deployed"
    deploy = start_deploy(tmp_path / "plan.json", space, system, run)
    watcher: subprocess.Popen[str] | None = None
    run_id = None
    try:
        live = await_live(run, deploy)
        run_id = live["run_id"]
        assert live["format"] == "perfros-bag/deploy-live@1" and live["pid"] == deploy.pid
        assert live["master_uri"].startswith("http://")
        watcher = subprocess.Popen([str(BIN), "watch", str(tmp_path / "plan.json"), "--deployment", str(run), "--json",
                                    "--window", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert watcher.stdout is not None
        steady = [json.loads(watcher.stdout.readline()) for _ in range(2)]
        for doc in steady:
            assert {"t", "nodes", "alarms"} <= set(doc)
            assert abs(doc["t"] - time.time()) < 30
            assert set(doc["nodes"]) == {"camera", "detector"}
            for n in doc["nodes"].values():
                assert {"expected_hz", "measured_hz", "cpu"} <= set(n) and n["cpu"] >= 0
            # the camera's rate, counted by its own publisher: its launch argument, 10 Hz (+- a frame per window)
            cam = doc["nodes"]["camera"]
            assert cam["expected_hz"] == 10 and abs(cam["measured_hz"] - 10) <= 1.0 / doc["seconds"] + 0.5, doc
            assert doc["alarms"] == [], doc["alarms"]
            # the chain's latency, from the stamps of the detector's own messages (hough_circles copies the
            # image's header): as many as its publisher counted in the window, each after its image was stamped
            [chain] = doc["chains"]
            m = chain["measured_ms"]
            det = doc["nodes"]["detector"]["topics"]["/detector/circles"]["messages"]
            assert m is not None and abs(m["messages"] - det) <= 2 and 0 < m["p50"] <= m["p95"] < 1000, (m, det)
            # the link carries the images: circles.png is 320 x 240 RGB, 230,400 bytes of pixels a frame
            [link] = doc["links"]
            assert link["between"] == ["robot1", "server"]
            per_frame_kB = link["measured_kBps"] / cam["topics"]["/camera/image_raw"]["measured_hz"]
            assert 230.4 <= per_frame_kB <= 230.6, per_frame_kB
        # a new plan through control.json (as watch --adapt --deployment sends one): the camera at 5 Hz.
        # The deploy restarts the camera alone: a new PID for it, the same for the detector, and the
        # camera's own publisher counts 5 Hz
        slower = json.loads((tmp_path / "plan.json").read_text())
        slower["nodes"]["camera"]["value"] = 5
        (tmp_path / "plan5.json").write_text(json.dumps(slower))
        (run / "control.tmp").write_text(json.dumps({"format": "perfros-bag/deploy-control@1", "seq": 1,
                                                     "plan": str(tmp_path / "plan5.json"), "why": ["test"]}))
        os.replace(run / "control.tmp", run / "control.json")
        rates, restart_docs = [], []
        for _ in range(8):
            doc = json.loads(watcher.stdout.readline())
            restart_docs.append(doc)
            rates.append(doc["nodes"]["camera"]["measured_hz"])
            if abs(rates[-1] - 5) <= 1.0 / doc["seconds"] + 0.5 and len(rates) > 1:
                break
        assert abs(rates[-1] - 5) <= 1.0 / doc["seconds"] + 0.5, rates
        # the deploy said it was restarting the camera (live.json `restarting`): never named dead meanwhile
        assert not [a for d in restart_docs for a in d["alarms"] if a["quantity"] == "alive"], restart_docs
        assert {d["nodes"]["camera"]["state"] for d in restart_docs} <= {"running", "restarting"}
        now = json.loads((run / "live.json").read_text())["nodes"]
        assert now["/camera"]["pid"] != live["nodes"]["/camera"]["pid"]
        assert now["/detector"]["pid"] == live["nodes"]["/detector"]["pid"]
        assert psutil_alive(now["/camera"]["pid"]) and psutil_alive(now["/detector"]["pid"])
        camera = now["/camera"]["pid"]
        killed = time.time()
        os.kill(camera, signal.SIGKILL)
        after: list[dict[str, Any]] = []
        while len(after) < 2:
            line = watcher.stdout.readline()
            if not line:
                break
            doc = json.loads(line)
            if doc["t"] > killed:
                after.append(doc)
        named = [a for d in after for a in d["alarms"] if a.get("node") == "camera" and a["quantity"] == "alive"]
        assert named, (after, watcher.wait(timeout=30), watcher.stderr.read() if watcher.stderr else "")
        assert {"quantity", "planned", "measured"} <= set(named[0])
        watcher.wait(timeout=60)
        assert watcher.returncode == 1, watcher.stderr.read() if watcher.stderr else ""
        deploy.wait(timeout=90)
    finally:
        stop_all(watcher, deploy)
    nothing_left(run, run_id)
