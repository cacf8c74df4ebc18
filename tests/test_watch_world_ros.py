"""A world change under a running ``deploy``, caught by ``watch`` (issue 30's RQ4, short):
the robot's link is re-shaped in place to a third of its rate (``control.json`` ``links``)
while a watcher is attached; the detector behind the link slows and ``watch`` names it.

Independent checks: the qdisc's rate and counters from ``tc -s -j qdisc show`` in the
robot's namespace (the kernel's own report: the new rate in bit/s, the same qdisc handle,
its byte counter still growing: changed in place, not re-created); the link's load in the
steady windows against bytes x rate (320 x 240 RGB = 230,400 bytes a frame times the
camera's frames), and after the drop judged against the new rate, the kernel's count of
what crossed never above it (the frames no longer fit: 2,304 kB/s into 2,000); the alarm, on the detector's rate,
within 2 whole windows of the change (the change is made right after a window ends).
Ctrl-C to the deploy in the middle of its run: afterwards no process with the run's tag,
no cgroup, no namespace (so no qdisc) of the run, and the watch itself exited.
"""

from __future__ import annotations

import json
import signal
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from perfros_bag.rosrun.network import tbf_rate_bit
from perfros_bag.sweep.control import write_control
from tests.test_sweep_e2e import BIN, _cli, _require_ros, _space
from tests.test_watch_ros import SYSTEM, await_live, nothing_left, start_deploy, stop_all

pytestmark = [pytest.mark.ros, pytest.mark.net]

FRAME_KB = 320 * 240 * 3 / 1000.0  # circles.png's pixels, a frame
LINK_KBPS = 6000.0  # SYSTEM's link: 10 Hz of frames (2,304 kB/s) fit, a third (2,000 kB/s) does not


def ctrl_c_on() -> None:
    """SIGINT back to its default in the child (a background shell starts jobs with it
    ignored), so that the deploy takes it as Ctrl-C."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def tbf(ns: str) -> list[dict[str, Any]]:
    done = subprocess.run(["tc", "-n", ns, "-s", "-j", "qdisc", "show"], capture_output=True, text=True, check=True)
    return [q for q in json.loads(done.stdout or "[]") if q.get("kind") == "tbf"]


def test_a_link_dropped_in_place_is_named_within_two_windows(tmp_path: Path) -> None:
    _require_ros()
    system = tmp_path / "system.yaml"
    system.write_text(yaml.safe_dump(SYSTEM, sort_keys=False))
    step = _cli("solve", str(system), "--problem", "1", "--method", "exact", "--out", str(tmp_path / "plan.json"))
    assert step.returncode == 0, step.stderr
    space = _space(tmp_path / "space.yaml", duration_s=4, settle_s=1, design="grid",
                   vary=[{"node": "camera", "parameter": {"name": "publish_rate"}, "arg": "camera_rate",
                          "values": [10]},
                         {"node": "detector", "parameter": {"name": "canny_threshold"}, "arg": "canny_threshold",
                          "values": [200]}])
    run = tmp_path / "deployed"
    # a real Ctrl-C, even when pytest runs in the background
    deploy = start_deploy(tmp_path / "plan.json", space, system, run, preexec_fn=ctrl_c_on)
    watcher: subprocess.Popen[str] | None = None
    run_id = None
    try:
        live = await_live(run, deploy)
        run_id = live["run_id"]
        assert live["links"] == [{"between": ["robot1", "server"], "bandwidth_kBps": LINK_KBPS}]
        ns = live["namespaces"]["robot1"]
        [before] = tbf(ns)
        assert before["options"]["rate"] == tbf_rate_bit(LINK_KBPS) / 8  # tc -j reports bytes/s
        watcher = subprocess.Popen([str(BIN), "watch", str(tmp_path / "plan.json"), "--deployment", str(run), "--json",
                                    "--window", "2"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert watcher.stdout is not None
        steady = [json.loads(watcher.stdout.readline()) for _ in range(2)]
        assert all(d["alarms"] == [] for d in steady), steady
        for doc in steady:  # bytes x rate: the link carries the camera's frames, 230.4 kB each
            [link] = doc["links"]
            frames = doc["nodes"]["camera"]["topics"]["/camera/image_raw"]["measured_hz"]
            assert 230.4 <= link["measured_kBps"] / frames <= 230.6, (link, frames)
            assert link["capacity_kBps"] == LINK_KBPS
        # the change, right after a window ended: the next two windows are whole ones after it
        write_control(run, None, None, ["test: a third of the link"],
                      links=[{"between": ["robot1", "server"], "bandwidth_kBps": LINK_KBPS / 3}])
        changed = time.time()
        deadline = time.monotonic() + 10
        while json.loads((run / "live.json").read_text())["links"][0]["bandwidth_kBps"] != LINK_KBPS / 3:
            assert time.monotonic() < deadline, "the deploy did not apply the control file"
            time.sleep(0.1)
        [now] = tbf(ns)
        assert now["handle"] == before["handle"] and now["bytes"] > before["bytes"]  # in place: counters kept
        assert now["options"]["rate"] == tbf_rate_bit(LINK_KBPS / 3) / 8
        after: list[dict[str, Any]] = []
        while len(after) < 2:
            doc = json.loads(watcher.stdout.readline())
            if doc["t"] - doc["seconds"] >= changed - 0.5:  # a window wholly after the change (0.5 s: the reading)
                after.append(doc)
            elif doc["t"] > changed:
                continue
        named = [a for a in after[-1]["alarms"] if a.get("node") == "detector" and a["quantity"] == "rate_hz"]
        assert named, after
        assert named[0]["planned"] == 10 and named[0]["measured"] < 10 * (1 - 0.025), named
        for doc in after:  # judged against the rate in force (the publishers' bytes, so not capped by it:
            [link] = doc["links"]  # the sockets' buffers take what the link has not passed yet)
            assert link["capacity_kBps"] == LINK_KBPS / 3, link
        # what the kernel passed since the change: never above the new rate (its bucket's burst aside)
        [end] = tbf(ns)
        seconds = time.time() - changed
        assert (end["bytes"] - now["bytes"]) / 1000.0 <= LINK_KBPS / 3 * seconds + end["options"]["burst"] / 1000.0
        stopped = time.monotonic()
        deploy.send_signal(signal.SIGINT)  # Ctrl-C in the middle of the run
        deploy.wait(timeout=90)
        assert time.monotonic() - stopped < 30, "the deploy did not stop on Ctrl-C"
        watcher.wait(timeout=60)
    finally:
        stop_all(watcher, deploy)
    nothing_left(run, run_id)
