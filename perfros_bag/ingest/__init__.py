"""Recording readers: ROS 1 bags, rosbag2 directories (sqlite3/mcap), loose .db3, plain MCAP.

:func:`read_recording` is the one entry point: it sniffs the format, reads per-topic counts,
receive times and payload bytes without deserialising a message (fast index paths, streaming
fallback) and returns :class:`~perfros_bag.ingest.stats.RecordingStats`. Files are read
through one mmap; the readers unmap the pages behind them as they go
(:func:`~perfros_bag.ingest._accum.release`), so the resident set stays small however
large the recording (80 MB peak RSS for 2 GB, docs/benchmarks.md). Anything broken
raises :class:`~perfros_bag.errors.InputError` (``"<path>: <problem>"``), never another
exception.
"""

from __future__ import annotations

from pathlib import Path

from perfros_bag.errors import InputError
from perfros_bag.fileio import require_regular
from perfros_bag.ingest.stats import RecordingStats, TopicStats

__all__ = ["RecordingStats", "TopicStats", "detect_format", "read_recording"]

ROS1_MAGIC = b"#ROSBAG V"
MCAP_MAGIC = b"\x89MCAP0\r\n"
SQLITE_MAGIC = b"SQLite format 3\0"
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
_FORMAT_OF_MAGIC = {ROS1_MAGIC: "ros1", MCAP_MAGIC: "mcap", SQLITE_MAGIC: "rosbag2-sqlite3",
                    ZSTD_MAGIC: "zstd"}


def read_head(path: Path) -> bytes:
    """The first 16 bytes of the file ``path`` (enough for :func:`sniff`); an empty file is an
    InputError, and so is a named pipe or device (it would block or never end)."""
    require_regular(path, "recording")
    with path.open("rb") as f:
        head = f.read(16)
    if not head:
        raise InputError(path, "empty file (0 bytes)")
    return head


def sniff(head: bytes) -> str | None:
    """'ros1', 'mcap', 'rosbag2-sqlite3' or 'zstd' from a file's first bytes; None if unknown."""
    return next((fmt for magic, fmt in _FORMAT_OF_MAGIC.items() if head.startswith(magic)), None)


def detect_format(path: str | Path) -> str:
    """'ros1', 'mcap', 'rosbag2-sqlite3' (loose .db3), 'rosbag2' (directory) or 'zstd'."""
    p = Path(path)
    if p.is_dir():
        return "rosbag2"
    fmt = sniff(read_head(p))
    if fmt is None:
        raise InputError(p, "unknown format: not a ROS 1 bag, MCAP file or rosbag2 recording")
    return fmt


def read_recording(path: str | Path, *, fast: bool = True) -> RecordingStats:
    """Per-topic statistics of a recording (file or rosbag2 directory).

    ``fast`` reads counts and times from the indexes (falling back to streaming where an index
    is missing or damaged); ``fast=False`` always streams every record. Both give identical
    numbers.
    """
    from perfros_bag.ingest._accum import describe

    p = Path(path)
    try:
        return _read(p, fast)
    except InputError:
        raise
    except Exception as exc:  # corrupt data can fail anywhere: one clear line, never a traceback
        raise InputError(p, describe(exc)) from None


def _read(p: Path, fast: bool) -> RecordingStats:
    from perfros_bag.ingest import mcapfile, rosbag1, rosbag2
    from perfros_bag.ingest.discover import storage_of

    if not p.exists():
        raise InputError(p, "no such file or directory")
    if p.is_file() and p.name == "metadata.yaml":
        p = p.parent
    if p.is_dir():
        acc, fmt = rosbag2.read_dir(p, fast)
        return acc.build(p, fmt)
    fmt = detect_format(p)
    if fmt == "ros1":
        with rosbag2.open_mmap(p) as mm:
            return rosbag1.read(p, mm, fast)
    if fmt == "mcap":
        with rosbag2.open_mmap(p) as mm:  # a loose rosbag2 storage file says itself whether payloads are zstd frames
            return mcapfile.read(mm, fast).build(p, "mcap")
    if fmt == "rosbag2-sqlite3":
        return rosbag2.read_sqlite(p, fast).build(p, "rosbag2-sqlite3")
    # zstd: a file-compressed rosbag2 storage file (.db3.zstd / .mcap.zstd)
    storage = storage_of(p)
    if storage is None:
        raise InputError(p, "zstd-compressed file that is not a .db3.zstd or .mcap.zstd")
    return rosbag2.read_storage_file(p, fast).build(p, "rosbag2-" + storage)
