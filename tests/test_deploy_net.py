"""``deploy`` across emulated computers: real, unmodified C++ nodes (Debian's image_publisher
and opencv_apps' hough_circles, fixtures/app) with the camera on a CPU-capped robot, the
detector on a server, and the camera's images crossing a veth link shaped with ``tc``.

Independent checks: the merged recording is read with Debian's rosbag API (rates, message
bytes, each topic's publisher); the bytes the link's qdisc passed against the image stream
the recording holds and against the shaped rate; the nodes' network namespaces from
``/proc/PID/ns/net`` while the run is on; the link's shared medium's queue against what the
link's two qdiscs passed; and afterwards nothing left: no process with the
run's tag, no cgroup, no namespace, no ``pfr-`` interface on the host. Ctrl-C in the middle
of a deploy leaves nothing either.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import psutil
import pytest
import yaml

from perfros_bag.rosrun.cgroups import leftover_groups
from perfros_bag.rosrun.network import leftover_namespaces
from perfros_bag.rosrun.processes import leftover_processes
from tests.conftest import communicate_or_stacks
from tests.test_casestudy_e2e import ROS_PY, _cgroups_work
from tests.test_sweep_e2e import APP, BIN, _cli, _require_ros, _space

pytestmark = [pytest.mark.ros, pytest.mark.net]

# Per topic: messages, payload bytes, first and last receive time, publisher (Debian's rosbag API).
BAG_TOPICS = r"""
import json, sys, rosbag
out = {}
with rosbag.Bag(sys.argv[1]) as bag:
    callers = {c.topic: (c.header.get("callerid") or b"").decode() for c in bag._get_connections()}
    for topic, raw, t in bag.read_messages(raw=True):
        s = out.setdefault(topic, {"n": 0, "bytes": 0, "t0": t.to_sec(), "t1": t.to_sec(),
                                   "callerid": callers.get(topic)})
        s["n"] += 1
        s["bytes"] += len(raw[1])
        s["t1"] = t.to_sec()
print(json.dumps(out))
"""


def _bag_topics(bag: Path) -> dict[str, dict[str, Any]]:
    done = subprocess.run([ROS_PY, "-c", BAG_TOPICS, str(bag)], capture_output=True, text=True, timeout=120,
                          check=True, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    topics: dict[str, dict[str, Any]] = json.loads(done.stdout)
    return topics


def _namespaces_work() -> bool:
    return os.geteuid() == 0 and subprocess.run(["ip", "netns", "list"], capture_output=True).returncode == 0


def _host_veths() -> list[str]:
    done = subprocess.run(["ip", "-o", "link", "show"], capture_output=True, text=True, check=False)
    return [line.split(":")[1].strip() for line in done.stdout.splitlines() if ": pfr-" in line]


@pytest.fixture(scope="module")
def deployed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """sweep (the detector's threshold; the camera at its 10 Hz default) -> init -> a robot
    and a server joined by a 3,000 kB/s link on a 3,000 kB/s shared medium -> characterise -> fit -> solve -> deploy."""
    _require_ros()
    d = tmp_path_factory.mktemp("net")
    space = _space(d / "space.yaml", duration_s=3, settle_s=1, design="one-at-a-time",
                   vary=[{"node": "detector", "parameter": {"name": "canny_threshold"}, "arg": "canny_threshold",
                          "values": [100, 200]}])
    rec = d / "rec"
    step = _cli("sweep", str(APP), "--space", str(space), "--out", str(rec), timeout=150)
    assert step.returncode == 0, step.stderr
    step = _cli("init", str(rec), "--out", str(d / "draft.yaml"))
    assert step.returncode == 0, step.stderr
    doc = yaml.safe_load((d / "draft.yaml").read_text())
    doc["computers"] += [{"name": "robot1", "kind": "robot", "capacity": 30},
                         {"name": "server", "kind": "server", "capacity": 60}]
    doc["links"] = [{"between": ["robot1", "server"], "bandwidth_kBps": 3000, "medium": "wifi"}]
    doc["media"] = [{"name": "wifi", "bandwidth_kBps": 3000}]
    home = {"camera": "robot1", "detector": "server"}
    for node in doc["nodes"]:
        node["residence"] = [home[node["name"]]]
    system = d / "system.yaml"
    system.write_text(yaml.safe_dump(doc, sort_keys=False))
    for args in (["characterise", str(rec), "--system", str(system), "--out", str(d / "char.csv")],
                 ["fit", str(system), str(d / "char.csv"), "--out", str(d / "model.json")],
                 ["solve", str(d / "model.json"), "--problem", "1", "--method", "exact",
                  "--out", str(d / "plan.json")]):
        step = _cli(*args)
        assert step.returncode == 0, (args[0], step.stderr)
    run = d / "deployed"
    proc = subprocess.Popen([str(BIN), "deploy", str(d / "plan.json"), str(APP), "--space", str(space), "--out",
                             str(run), "--duration", "4", "--system", str(system)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    seen: dict[str, int] = {}  # ROS node -> inode of its network namespace, while it runs
    try:
        deadline = time.monotonic() + 120
        while proc.poll() is None and time.monotonic() < deadline:
            for p in psutil.process_iter(["pid", "cmdline"]):
                cmd = p.info["cmdline"] or []
                if any(a in ("__name:=camera", "__name:=detector") for a in cmd) \
                        and _env(p).get("ROS_HOME", "").startswith(str(run)):
                    name = next(a.split("=", 1)[1] for a in cmd if a.startswith("__name:="))
                    try:
                        seen[name] = os.stat(f"/proc/{p.pid}/ns/net").st_ino
                    except OSError:
                        pass
            time.sleep(0.3)
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    return {"d": d, "run": run, "rc": proc.returncode, "stderr": stderr, "seen": seen,
            "plan": json.loads((d / "plan.json").read_text())}


def test_a_plan_runs_across_a_shaped_link_and_validates(deployed: dict[str, Any]) -> None:
    run, plan = deployed["run"], deployed["plan"]
    assert deployed["rc"] in (0, 1), deployed["stderr"]
    assert "Traceback" not in deployed["stderr"]
    assert {n: v["computer"] for n, v in plan["nodes"].items()} == {"camera": "robot1", "detector": "server"}
    record = json.loads((run / "deploy.json").read_text())
    network = record["network"]
    if not _namespaces_work():
        assert network["mode"] == "unshaped" and network["reason"]
        return
    assert network["mode"] == "netns" and network["shaped"]
    assert {"robot1", "server"} <= set(network["namespaces"])
    # each node ran in its own computer's namespace, not in this one
    own = os.stat("/proc/self/ns/net").st_ino
    assert set(deployed["seen"]) == {"camera", "detector"}
    assert deployed["seen"]["camera"] != deployed["seen"]["detector"]
    assert own not in deployed["seen"].values()
    if _cgroups_work():
        assert record["cpu_cap"]["mode"] != "uncapped"
        assert record["cpu_cap"]["cores"] == {"robot1": 0.3, "server": 0.6}
    # the merged recording, by Debian's rosbag API: both computers' topics, their publishers kept
    topics = _bag_topics(run / "run.bag")
    image = next(t for t in topics if t.endswith("image_raw"))
    assert topics[image]["callerid"] == "/camera"
    assert any(v["callerid"] == "/detector" and v["n"] > 0 for v in topics.values())
    rate = (topics[image]["n"] - 1) / (topics[image]["t1"] - topics[image]["t0"])
    assert abs(rate / 10.0 - 1) < 0.1  # the camera's default rate
    # the link carried the image stream (the qdisc's bytes include TCP/IP headers: a few % more),
    # within its shaped rate
    stream_kBps = topics[image]["bytes"] / (topics[image]["t1"] - topics[image]["t0"]) / 1000
    up = next(x for x in network["links_measured"] if x["from"] == "robot1")
    assert 0.9 * stream_kBps < up["sent_kBps"] < 1.25 * stream_kBps, (up, stream_kBps)
    assert up["sent_kBps"] <= 1.02 * up["shaped_kBps"]
    # the medium's one queue (an IFB on the server) carried both directions of the link: what
    # the two ends' qdiscs passed, counted at the same moments
    [medium] = network["media"]
    assert medium["emulated"] and medium["hub"] == "server" and medium["links"] == [0]
    [wifi] = network["media_measured"]
    both = sum(x["sent_kBps"] for x in network["links_measured"])
    assert wifi["medium"] == "wifi" and abs(wifi["sent_kBps"] / both - 1) < 0.05, (wifi, both)
    assert wifi["sent_kBps"] <= 1.02 * wifi["shaped_kBps"]
    validation = json.loads((run / "validation.json").read_text())
    assert validation["overall"]["deviation_pct"] <= 5.0, validation["overall"]
    assert deployed["rc"] == 0
    [link] = validation["links"]
    assert link["between"] == ["robot1", "server"] and not link["overloaded"]
    assert abs(link["measured_kBps"] / stream_kBps - 1) < 0.1


def test_a_deploy_leaves_no_namespace_cgroup_process_or_interface(deployed: dict[str, Any]) -> None:
    record = json.loads((deployed["run"] / "deploy.json").read_text())
    assert record["leftover_namespaces"] == [] and record["leftover_cgroups"] == []
    # the machine's speed as the run began: in deploy.json, the manifest and both traces
    entry = yaml.safe_load((deployed["run"] / "manifest.yaml").read_text())["recordings"][0]
    assert record["speed_factor"] is not None and record["speed_factor"] > 0
    # measured again as the recording's window ended: the same workload's factor, within the
    # spread this machine shows (docs/benchmarks.md: 0.4-1.1)
    assert record["speed_factor_end"] is not None and 0.05 < record["speed_factor_end"] < 5
    assert entry["speed_factor"] == record["speed_factor"]
    for trace in ("run.cpu.csv", "run.host.cpu.csv"):
        assert "# speed_factor=" in (deployed["run"] / trace).read_text()
    assert leftover_namespaces(f"d{record['run_id']}") == []
    assert leftover_groups(run_id=record["run_id"]) == []
    assert leftover_processes(record["run_id"]) == []
    assert _host_veths() == []


def test_ctrl_c_during_a_networked_deploy_leaves_nothing(deployed: dict[str, Any], tmp_path: Path) -> None:
    d = deployed["d"]
    run = tmp_path / "interrupted"
    proc = subprocess.Popen([str(BIN), "deploy", str(d / "plan.json"), str(APP), "--space", str(d / "space.yaml"),
                             "--out", str(run), "--duration", "30", "--system", str(d / "system.yaml")],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and proc.poll() is None:
            if any("__name:=detector" in (p.info["cmdline"] or []) and _env(p).get("ROS_HOME", "").startswith(str(run))
                   for p in psutil.process_iter(["cmdline"])):
                break
            time.sleep(0.2)
        assert proc.poll() is None, proc.stderr.read() if proc.stderr else ""
        names = leftover_namespaces()
        if _namespaces_work():
            assert any(n.startswith("pfr-d") for n in names)
        tags = {env["PERFROS_CASESTUDY_RUN"] for env in map(_env, psutil.process_iter())
                if "PERFROS_CASESTUDY_RUN" in env and env.get("ROS_HOME", "").startswith(str(run))}
        assert len(tags) == 1
        proc.send_signal(signal.SIGINT)
        _, stderr = communicate_or_stacks(proc, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 130, stderr
    assert "Traceback" not in stderr
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline and any(leftover_processes(t) for t in tags):
        time.sleep(0.2)
    for tag in tags:
        assert leftover_processes(tag) == [], tag
        assert leftover_groups(run_id=tag) == [], tag
        assert leftover_namespaces(f"d{tag}") == [], tag
    assert _host_veths() == []


def _env(p: psutil.Process) -> dict[str, str]:
    try:
        return dict(p.environ())
    except (psutil.Error, OSError):
        return {}
