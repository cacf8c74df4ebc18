"""A pipeline interrupted on its own (a SIGINT or SIGTERM to its process alone, not to its group)
lets the step it runs clean up: the step gets one SIGINT and time, never a SIGKILL. A `deploy`
killed outright would leave its nodes, cgroups and namespaces behind."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psutil
import pytest

PIPELINES = Path(__file__).resolve().parent.parent / "pipelines"

STEP = """
import os, pathlib, sys, time
d = pathlib.Path(sys.argv[1])
(d / "step.pid").write_text(str(os.getpid()))
try:
    while True:
        time.sleep(0.05)
except KeyboardInterrupt:
    time.sleep(1.0)  # its clean-up takes a while
    (d / "cleaned").write_text(str(os.getpgid(0)))
    sys.exit(130)
"""

PIPELINE = """
import sys
from pathlib import Path
sys.path.insert(0, sys.argv[1])
from rich.console import Console
from _common import interrupt_on_sigterm, run_shown
interrupt_on_sigterm()
d = Path(sys.argv[2])
run_shown([sys.executable, str(d / "step.py"), str(d)], root=d, program=d / "x", commands=[],
          console=Console(stderr=True))
"""


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_the_running_step_cleans_up_when_the_pipeline_alone_is_interrupted(tmp_path: Path, sig: int) -> None:
    (tmp_path / "step.py").write_text(STEP)
    pipeline = subprocess.Popen([sys.executable, "-c", PIPELINE, str(PIPELINES), str(tmp_path)],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 30
        while not (tmp_path / "step.pid").exists():
            assert time.monotonic() < deadline and pipeline.poll() is None, pipeline.communicate()
            time.sleep(0.05)
        step = int((tmp_path / "step.pid").read_text())
        os.kill(pipeline.pid, sig)
        _, err = pipeline.communicate(timeout=30)
    finally:
        if pipeline.poll() is None:
            pipeline.kill()
    assert pipeline.returncode != 0
    assert "KeyboardInterrupt" in err
    # the step heard the interrupt, cleaned up in its own session, and is gone
    assert (tmp_path / "cleaned").exists()
    assert int((tmp_path / "cleaned").read_text()) != os.getpgid(0)
    assert not psutil.pid_exists(step) or psutil.Process(step).status() == psutil.STATUS_ZOMBIE
