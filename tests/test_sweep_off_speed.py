"""sweep --repeat-off-speed without ROS: runs recorded while the machine's speed reference was
off the sweep's median are recorded again, and the recording nearer the median is kept (its bag,
its trace and its manifest entry together); a farther repeat is deleted."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import perfros_bag.sweep.runner as runner
from perfros_bag.characterisation.manifest import load_manifest
from perfros_bag.sweep.graph import Graph

ROOT = Path(__file__).resolve().parent.parent


def test_median_and_off_speed_against_a_hand_count() -> None:
    entries: dict[str, dict[str, Any]] = {k: {"speed_factor": f} for k, f in
                                          {"a": 0.76, "b": 0.45, "c": 0.74, "d": 0.95, "e": None}.items()}
    assert runner.median_speed(entries) == pytest.approx(0.75)  # of 0.45, 0.74, 0.76, 0.95
    # within 0.85 x 0.75 = 0.6375 .. 0.75 / 0.85 = 0.882: b is slower, d faster
    assert runner.off_speed(entries, 0.75) == ["b", "d"]
    assert runner.off_speed(entries, None) == [] and runner.median_speed({"e": {}}) is None


class _FakeRecorder:
    """record_run that writes <run>.bag and <run>.cpu.csv with the next speed of its list."""

    def __init__(self, speeds: dict[str, list[float]]) -> None:
        self.speeds, self.calls = speeds, []  # type: ignore[var-annotated]

    def __call__(self, launch: Any, space: Any, run: Any, out: Path, **_: Any) -> Graph:
        speed = self.speeds[run.name].pop(0)
        self.calls.append((run.name, out.name, speed))
        out.mkdir(parents=True, exist_ok=True)
        (out / f"{run.name}.bag").write_bytes(f"bag {speed}".encode())
        (out / f"{run.name}.cpu.csv").write_text(f"# speed_factor={speed}\ntime,pid,node,process,cpu_percent\n")
        return Graph((), ())


def test_off_speed_runs_are_recorded_again_and_the_nearer_recording_is_kept(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    runs = [r.name for r in runner.plan_runs(runner.load_space(ROOT / "fixtures/app/space.yaml"),
                                             runner.read_launch(ROOT / "fixtures/app/app.launch").args)]
    assert len(runs) == 4
    first, slow, fast, same = runs
    fake = _FakeRecorder({first: [0.76], slow: [0.45, 0.52, 0.74], fast: [0.95, 0.99, 0.97], same: [0.75]})
    monkeypatch.setattr(runner, "record_run", fake)
    monkeypatch.setattr(runner, "require_ros_tools", lambda: None)
    out = tmp_path / "sweep"
    result = runner.sweep(ROOT / "fixtures/app/app.launch", ROOT / "fixtures/app/space.yaml", out, repeat_off_speed=2)
    # median of 0.76, 0.45, 0.95, 0.75 = 0.755: slow and fast are off; slow nears it twice, fast never
    assert [c[0] for c in fake.calls] == [first, slow, fast, same, slow, fast, slow, fast]
    assert all(c[1] == ".respeed" for c in fake.calls[4:])
    assert result.repeated == [slow, slow] and result.recorded == runs
    speeds = {Path(e.path).stem: e.speed_factor for e in load_manifest(out / "manifest.yaml").recordings}
    assert speeds == {first: 0.76, slow: 0.74, fast: 0.95, same: 0.75}
    # the kept files are the ones the manifest names: the bag and the trace of the same recording
    assert (out / f"{slow}.bag").read_bytes() == b"bag 0.74" and (out / f"{fast}.bag").read_bytes() == b"bag 0.95"
    from perfros_bag.cpu.trace import trace_speed

    assert trace_speed(out / f"{slow}.cpu.csv") == pytest.approx(0.74)
    assert not (out / ".respeed").exists()


def test_no_repeat_by_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    runs = [r.name for r in runner.plan_runs(runner.load_space(ROOT / "fixtures/app/space.yaml"),
                                             runner.read_launch(ROOT / "fixtures/app/app.launch").args)]
    fake = _FakeRecorder({r: [s] for r, s in zip(runs, (0.76, 0.45, 0.95, 0.75), strict=True)})
    monkeypatch.setattr(runner, "record_run", fake)
    monkeypatch.setattr(runner, "require_ros_tools", lambda: None)
    result = runner.sweep(ROOT / "fixtures/app/app.launch", ROOT / "fixtures/app/space.yaml", tmp_path / "s")
    assert len(fake.calls) == 4 and result.repeated == []
