"""`make test` runs two workers; the tests that start real ROS nodes, cgroups or namespaces must
share one of them (tests/conftest.py). Checked on a throw-away suite under the installed pytest
and pytest-xdist: without ``tryfirst`` on the conftest hook, or under pytest 9 (xdist 3.8 renames
``item._nodeid``, which pytest 9 no longer reads), they silently ran side by side, and on CI a
replayed camera starved its detector."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

ROS_FILE = '''
import os, time, pytest
pytestmark = pytest.mark.ros

@pytest.mark.parametrize("i", range(6))
def test_ros(i):
    time.sleep(0.1)
    with open(os.environ["WHO"], "a") as f:
        f.write(f"ros {os.environ['PYTEST_XDIST_WORKER']}\\n")
'''

PLAIN_FILE = '''
import os, time, pytest

@pytest.mark.parametrize("i", range(6))
def test_plain(i):
    time.sleep(0.1)
    with open(os.environ["WHO"], "a") as f:
        f.write(f"plain {os.environ['PYTEST_XDIST_WORKER']}\\n")

@pytest.mark.net
def test_net():
    with open(os.environ["WHO"], "a") as f:
        f.write(f"ros {os.environ['PYTEST_XDIST_WORKER']}\\n")
'''


def test_ros_and_net_tests_share_one_worker_under_loadgroup(tmp_path: Path) -> None:
    shutil.copy(Path(__file__).with_name("conftest.py"), tmp_path / "conftest.py")
    (tmp_path / "test_a_ros.py").write_text(ROS_FILE)
    (tmp_path / "test_b_plain.py").write_text(PLAIN_FILE)
    who = tmp_path / "who.txt"
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-n", "2", "--dist", "loadgroup", "-p", "no:cacheprovider",
         "-W", "ignore::pytest.PytestUnknownMarkWarning", str(tmp_path)],
        cwd=tmp_path, env={**os.environ, "WHO": str(who)},
        capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 0, done.stdout + done.stderr
    lines = [line.split() for line in who.read_text().splitlines()]
    ros = {w for kind, w in lines if kind == "ros"}
    assert len([k for k, _ in lines if k == "ros"]) == 7
    assert len(ros) == 1, f"ROS tests ran on {sorted(ros)}"
    # the rest still spread: both workers ran something
    assert {w for _, w in lines} == {"gw0", "gw1"}
