"""The recorders of a run: ``rosbag record`` (Debian's) and ``perfros-bag record-cpu``."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.rosrun.processes import Processes, Started

ROSBAG = "rosbag"
# Debian's rosbag C++ recorder: what `rosbag record` (a Python wrapper) runs; starting it
# directly saves the wrapper's ~1 s of imports.
RECORD_BIN = Path("/usr/lib/rosbag/record")


#: ``rosbag record`` stops recording (it keeps running) when less than this is free on the
#: recording's disk: its ``--min-space`` default, 1 GB.
ROSBAG_MIN_FREE_BYTES = 1 << 30


def require_free_space(directory: Path) -> None:
    """An :class:`InputError` when ``directory``'s disk has less room than ``rosbag record``
    needs to record at all (checked before anything starts)."""
    import shutil

    free = shutil.disk_usage(directory).free
    if free < ROSBAG_MIN_FREE_BYTES:
        raise InputError(directory, f"only {free / 1e6:.1f} MB free on its disk; rosbag record refuses to "
                         f"record with less than {ROSBAG_MIN_FREE_BYTES / 2**30:g} GiB free")


def rosbag_argv(bag: Path, topics: list[str] | None, node_name: str, exclude: str | None = None) -> list[str]:
    """``rosbag record -O bag`` of ``topics`` (None: every topic, ``-a``, but those the regex
    ``exclude`` matches) as ROS node ``node_name``."""
    recorder = [str(RECORD_BIN)] if RECORD_BIN.exists() else [ROSBAG, "record"]
    which = ["-a", *(["-x", exclude] if exclude else [])] if topics is None else topics
    return [*recorder, "-O", str(bag), *which, f"__name:={node_name}"]


def start_rosbag(procs: Processes, name: str, bag: Path, topics: list[str] | None, node_name: str,
                 log: Path, cwd: Path, exclude: str | None = None) -> Started:
    """Start :func:`rosbag_argv`."""
    return procs.start(name, rosbag_argv(bag, topics, node_name, exclude), log, cwd=cwd)


def merge_bags(parts: list[Path], dest: Path, start_ns: int | None = None, end_ns: int | None = None) -> None:
    """One ROS 1 bag ``dest`` holding every message of ``parts`` (bags recorded at the same
    time on different computers) received in [``start_ns``, ``end_ns``], in time order,
    each connection with its message definition and publisher (``callerid``) as recorded:
    rosbags reads and writes them, the payloads are copied as they are."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag1 import Writer

    tmp = dest.with_name(dest.name + ".part")
    tmp.unlink(missing_ok=True)
    with AnyReader(parts) as reader:
        writer = Writer(tmp)
        writer.open()
        try:
            made: dict[int, Any] = {}
            added: dict[tuple[str, str, str | None], Any] = {}  # a topic both computers recorded: one connection
            for conn in reader.connections:
                callerid = getattr(conn.ext, "callerid", None)
                key = (conn.topic, conn.msgtype, callerid)
                if key not in added:
                    added[key] = writer.add_connection(
                        conn.topic, conn.msgtype, msgdef=conn.msgdef.data, md5sum=conn.digest,
                        callerid=callerid, latching=getattr(conn.ext, "latching", None))
                made[id(conn)] = added[key]
            for conn, stamp, raw in reader.messages(start=start_ns, stop=None if end_ns is None else end_ns + 1):
                writer.write(made[id(conn)], stamp, raw)
        finally:
            writer.close()
    tmp.replace(dest)


def start_record_cpu(procs: Processes, patterns: list[str], interval: float, trace: Path, log: Path,
                     cwd: Path) -> Started:
    """``perfros-bag record-cpu`` (this interpreter) of the processes matching ``patterns``;
    it creates :func:`cpu_ready_path` of ``trace`` once its first sample is taken."""
    argv = [sys.executable, "-m", "perfros_bag", "record-cpu", "--quiet"]
    for pattern in patterns:
        argv += ["--match", pattern]
    ready = cpu_ready_path(trace)
    ready.unlink(missing_ok=True)
    argv += ["--interval", f"{interval:g}", "--out", str(trace), "--ready", str(ready)]
    return procs.start("record-cpu", argv, log, cwd=cwd)


def cpu_ready_path(trace: Path) -> Path:
    """The file record-cpu creates once it samples (a loaded machine may take seconds to
    start it: a recording waits for it, or its trace would miss the start or be empty)."""
    return trace.with_name(trace.name + ".ready")
