"""Timing helpers, and the cached data sets, shared by the benchmark scripts (run as
scripts: this folder is on sys.path)."""

from __future__ import annotations

import shutil
import statistics
import time
from collections.abc import Callable
from pathlib import Path


def recording_once(data: Path, folder: str, fmt: str, write: Callable[[Path], None]) -> Path:
    """``data/folder/rec...`` (``rec.bag`` for ROS 1, ``rec.mcap`` for plain MCAP, else a
    rosbag2 directory ``rec``) as ``write(target)`` writes it, unless a complete one is
    there (a ``.complete`` marker, touched once the writing finished)."""
    target = data / folder / ("rec.bag" if fmt == "ros1" else "rec.mcap" if fmt == "mcap-zstd" else "rec")
    done = target.parent / ".complete"
    if done.exists():
        return target
    shutil.rmtree(target.parent, ignore_errors=True)
    target.parent.mkdir(parents=True)
    t = time.perf_counter()
    write(target)
    print(f"  generated {target.relative_to(data)} in {time.perf_counter() - t:.1f} s", flush=True)
    done.touch()
    return target


def timings(fn: Callable[[], object], repeat: int) -> list[float]:
    """The wall-clock seconds of ``repeat`` runs of ``fn``."""
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return times


def best(fn: Callable[[], object], repeat: int) -> float:
    """The fastest of ``repeat`` wall-clock runs of ``fn``, in seconds."""
    return min(timings(fn, repeat))


def median(fn: Callable[[], object], repeat: int) -> float:
    """The median of ``repeat`` wall-clock runs of ``fn``, in seconds."""
    return statistics.median(timings(fn, repeat))
