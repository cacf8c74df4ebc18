"""Find the recordings in a directory: ROS 1 bags, MCAP files, loose .db3 and rosbag2 directories.

Rules (documented for ``characterise DIR``):

* a path that is itself a recording (a file, or a directory with ``metadata.yaml``) is the one
  recording;
* in a directory, every ``.bag``, ``.mcap``, ``.db3`` (also ``.mcap.zstd`` / ``.db3.zstd``) file
  is a recording of its own;
* a sub-directory is one rosbag2 recording when it has a ``metadata.yaml`` or holds storage
  files (``.db3`` / ``.mcap``) and no sub-directory (a split bag without metadata); other
  sub-directories are searched in turn.

Hidden entries (``.name``) and SQLite sidecars (``-wal``, ``-shm``) are skipped. Results are in
natural order (``run2`` before ``run10``).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError

#: rosbag2 storage file suffix -> storage plugin; ``.zstd`` may follow (file compression)
STORAGE_PLUGINS = {".db3": "sqlite3", ".mcap": "mcap"}
STORAGE_SUFFIXES = (*STORAGE_PLUGINS, *(s + ".zstd" for s in STORAGE_PLUGINS))
FILE_SUFFIXES = (".bag", *STORAGE_SUFFIXES)


def natural_key(p: Path) -> list[Any]:
    """Sort key of a path's name in natural order (``run2`` before ``run10``)."""
    return [int(t) if t.isdigit() else t for t in re.split(r"(\d+)", p.name)]


def storage_of(path: Path) -> str | None:
    """'sqlite3' / 'mcap' from the suffix (``.zstd`` file compression stripped), else None."""
    name = path.name[:-5] if path.name.endswith(".zstd") else path.name
    return STORAGE_PLUGINS.get(Path(name).suffix)


def is_recording_file(p: Path) -> bool:
    return p.is_file() and p.name.endswith(FILE_SUFFIXES) and not p.name.startswith(".")


def is_rosbag2_dir(p: Path) -> bool:
    """A directory with metadata.yaml, or only storage files and no sub-directory."""
    if not p.is_dir():
        return False
    if (p / "metadata.yaml").is_file():
        return True
    entries = [e for e in p.iterdir() if not e.name.startswith(".")]
    return (any(e.is_file() and e.name.endswith(STORAGE_SUFFIXES) for e in entries)
            and not any(e.is_dir() for e in entries))


def find_recordings(root: str | Path) -> list[Path]:
    """Every recording at or under ``root`` (see the module doc for the rules)."""
    base = Path(root)
    if not base.exists():
        raise InputError(base, "no such file or directory")
    if base.is_file() or (base / "metadata.yaml").is_file():
        return [base]
    found: list[Path] = []
    _walk(base, found)
    return found


def _walk(d: Path, found: list[Path]) -> None:
    try:
        entries = sorted(d.iterdir(), key=natural_key)
    except OSError as exc:
        raise InputError(d, exc.strerror or str(exc)) from None
    for e in entries:
        if e.name.startswith("."):
            continue
        if e.is_dir():
            if is_rosbag2_dir(e):
                found.append(e)
            else:
                _walk(e, found)
        elif is_recording_file(e):
            found.append(e)
