"""The readers unmap the pages of the recording they have read (issue 7: bounded RSS).

No timing: just before each reader's mmap is closed, the resident size of that file's mapping
is read from ``/proc/self/smaps`` (psutil ``memory_maps``). Reading a ~50 MB recording must
leave only a small part of it mapped; the same read with the release helper switched off
(the control) leaves much more mapped, so the check can fail. Results stay the same either
way.
"""

from __future__ import annotations

import mmap
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import psutil
import pytest

from perfros_bag.ingest import _accum, mcapfile, read_recording, rosbag1, rosbag2, sqlitepages
from perfros_bag.ingest.stats import RecordingStats
from tests.bench.gen_corpus import TopicSpec, default_topics, write_recording

MB = 1 << 20


def mapped_rss(path: Path) -> int:
    """Resident bytes of this process's mappings of ``path``."""
    target = str(path.resolve())
    return sum(m.rss for m in psutil.Process().memory_maps(grouped=True) if m.path == target)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("memory")
    out = {"ros1": root / "big.bag", "mcap": root / "big.mcap"}
    write_recording(out["ros1"], "ros1", default_topics(), 35.0, seed=1)  # ~50 MB each
    write_recording(out["mcap"], "mcap", default_topics(), 35.0, seed=2)
    # small messages: the sqlite rows live in the B-tree leaf pages, which the decoder reads
    small = [TopicSpec("/a", 4000.0, 900), TopicSpec("/b", 1000.0, 1500)]
    write_recording(root / "db", "rosbag2-sqlite3", small, 6.0, seed=3)
    out["rosbag2-sqlite3"] = next((root / "db").glob("*.db3"))
    return out


def read_measured(path: Path, fast: bool, monkeypatch: pytest.MonkeyPatch) -> tuple[RecordingStats, int]:
    """``read_recording(path)`` and the file's resident mapped bytes just before it is unmapped."""
    seen: list[int] = []
    real_open, real_messages = rosbag2.open_mmap, sqlitepages.read_messages

    @contextmanager
    def open_mmap(p: Path) -> Iterator[mmap.mmap]:
        with real_open(p) as mm:
            yield mm
            seen.append(mapped_rss(p))

    def read_messages(mm: mmap.mmap, root: int, rows: int) -> object:
        result = real_messages(mm, root, rows)
        seen.append(mapped_rss(path))
        return result

    monkeypatch.setattr(rosbag2, "open_mmap", open_mmap)
    monkeypatch.setattr(sqlitepages, "read_messages", read_messages)
    target = path.parent if path.suffix == ".db3" else path
    stats = read_recording(target, fast=fast)
    assert len(seen) == 1, "the reader did not go through the measured mmap"
    return stats, seen[0]


CASES = [("ros1", True), ("ros1", False), ("mcap", True), ("mcap", False), ("rosbag2-sqlite3", True)]


@pytest.mark.parametrize(("fmt", "fast"), CASES)
def test_reader_releases_pages(fmt: str, fast: bool, recordings: dict[str, Path],
                               monkeypatch: pytest.MonkeyPatch) -> None:
    path = recordings[fmt]
    size = path.stat().st_size
    assert size > 30 * MB
    path.read_bytes()  # in the page cache, so a touched page maps at once
    monkeypatch.setattr(_accum, "RELEASE_STEP", 1 * MB)  # streaming (rosbag1, mcap): release every 1 MB
    stats, resident = read_measured(path, fast, monkeypatch)
    assert stats.messages > 1000
    assert resident < size // 10, f"{resident / MB:.1f} MB of a {size / MB:.0f} MB file still mapped"

    # control: the same read without releasing keeps far more of the file mapped
    def keep(mm: mmap.mmap, start: int, end: int) -> None:
        return None

    for module in (_accum, rosbag1, mcapfile, sqlitepages):
        monkeypatch.setattr(module, "release", keep)
    control, resident_control = read_measured(path, fast, monkeypatch)
    assert resident_control > size // 4, f"control: only {resident_control / MB:.1f} MB mapped"
    print(f"{fmt} fast={fast}: {size / MB:.0f} MB file, {resident / MB:.2f} MB mapped, "
          f"{resident_control / MB:.1f} MB without release")
    assert resident_control > 3 * resident
    assert _same(control, stats)


def _same(a: RecordingStats, b: RecordingStats) -> bool:
    if list(a.topics) != list(b.topics):
        return False
    return all(x.messages == y.messages and x.bytes == y.bytes and x.msgtype == y.msgtype
               and np.array_equal(x.times_ns, y.times_ns)
               for x, y in zip(a.topics.values(), b.topics.values(), strict=True))
