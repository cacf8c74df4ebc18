"""``header.stamp`` of every message of the stamped topics, read in the readers' own pass.

A message whose type starts with ``std_msgs/Header`` has its stamp at a fixed place:

* ROS 1 serialisation: after the recorded Header's leading fixed-size fields (ROS 1's
  ``uint32 seq``: bytes 4-12 of the payload; :func:`~perfros_bag.ingest.decode.stamp_offset`);
* CDR (ROS 2): a 4-byte encapsulation header (``00 01`` little-endian, ``00 00`` big-endian),
  then ``int32 sec, uint32 nanosec`` -> bytes 4-12.

Which topics are stamped is decided by rosbags from the definitions stored in the recording
(:func:`perfros_bag.ingest.decode.starts_with_header`), parsed from what the readers' index
pass already holds: a ROS 1 bag's connection records (:attr:`rosbag1.Connection.msgdef`), an
MCAP summary's schemas (:attr:`mcapfile.Summary.definitions`), a rosbag2 sqlite3 file's
``message_definitions`` table. A :class:`Finder` is handed to the readers
(:data:`~perfros_bag.ingest._payload.StampFinder`): given their index it says which
connections to read the stamps of, and the readers gather them in the same pass as counts
and sizes (:func:`rosbag1.read_chunks <perfros_bag.ingest.rosbag1.read_chunks>`,
:func:`mcapfile.read_chunks <perfros_bag.ingest.mcapfile.read_chunks>`,
:func:`rosbag2.read_sqlite <perfros_bag.ingest.rosbag2.read_sqlite>`: the blobs' first bytes
from the C page walk). :func:`read_with_stamps` is that one pass over a recording.

Every structural fact is checked; anything unexpected (another CDR encapsulation, a payload
shorter than a header, an index that disagrees with its chunk) raises
:class:`~perfros_bag.ingest._accum.NoIndex` and the caller decodes with the libraries instead
(:mod:`perfros_bag.ingest.decode`). tests/test_contents.py proves these stamps equal the
libraries' full deserialisation on every stamped message of shared/realbags and of generated
recordings.
"""

from __future__ import annotations

import sqlite3
from pathlib import Path
from typing import Any

import numpy as np

from perfros_bag.ingest import mcapfile, rosbag1
from perfros_bag.ingest._accum import I64, Accumulator, NoIndex
from perfros_bag.ingest._payload import StampAt
from perfros_bag.ingest.decode import TopicType, Undecodable, channel_types, topic_type

#: topic -> (receive/log times ns, header stamps ns), one entry per message, in file order
Stamps = dict[str, tuple[I64, I64]]


def ros1_types(index: rosbag1.BagIndex) -> dict[int, TopicType]:
    """Connection id -> :class:`TopicType`, rosbags parsing each connection record's
    ``message_definition`` (kept in the index)."""
    from rosbags.typesys.msg import normalize_msgtype

    from perfros_bag.ingest.decode import typestore_from_definitions

    def name(msgtype: str) -> str:
        try:
            return str(normalize_msgtype(msgtype))
        except Exception:  # a type name rosbags cannot read: its topic is not stamped
            return msgtype

    typestore = typestore_from_definitions(
        (conn.msgtype, "ros1msg", conn.msgdef) for conn in index.connections.values() if conn.msgdef)
    return {cid: topic_type(typestore, conn.topic, name(conn.msgtype), "ros1")
            for cid, conn in index.connections.items()}


def mcap_types(summary: mcapfile.Summary) -> dict[int, TopicType]:
    """Channel id -> :class:`TopicType` of an MCAP file from its summary's schemas."""
    schemas = {sid: (summary.schemas.get(sid, ""), enc, data.decode("utf-8", "replace"))
               for sid, (enc, data) in summary.definitions.items()}
    return channel_types(schemas, ((cid, ch.topic, ch.schema_id, ch.encoding)
                                   for cid, ch in summary.channels.items()))


def sqlite_types(con: sqlite3.Connection) -> dict[int, TopicType]:
    """Topic id -> :class:`TopicType` of a rosbag2 sqlite3 file: rosbags parses the
    ``message_definitions`` table (rosbag2 >= Iron); a file without one uses rosbags'
    standard ROS 2 types (as its AnyReader does)."""
    from rosbags.typesys.msg import normalize_msgtype

    from perfros_bag.ingest.decode import standard_typestore, typestore_from_definitions

    try:
        stored = [(str(t), str(e), str(d)) for t, e, d in con.execute(
            "SELECT topic_type, encoding, encoded_message_definition FROM message_definitions") if d]
    except sqlite3.Error:  # older rosbag2: no such table
        stored = []
    typestore = typestore_from_definitions(stored) if stored else standard_typestore()
    return {int(tid): topic_type(typestore, str(name), normalize_msgtype(str(mtype or "")), str(fmt or "cdr"))
            for tid, name, mtype, fmt in con.execute("SELECT id, name, type, serialization_format FROM topics")}


class Finder:
    """The :data:`~perfros_bag.ingest._payload.StampFinder` the readers call with their index:
    the stamped connections and where their stamps are. Keeps every topic's
    :class:`TopicType` it saw in :attr:`types` (the first file's, for a topic in several)."""

    def __init__(self) -> None:
        self.types: dict[str, TopicType] = {}

    def __call__(self, source: Any) -> dict[int, StampAt]:
        if isinstance(source, rosbag1.BagIndex):
            by_id = ros1_types(source)
        elif isinstance(source, mcapfile.Summary):
            by_id = mcap_types(source)
        elif isinstance(source, sqlite3.Connection):
            by_id = sqlite_types(source)
        else:
            raise TypeError(f"no stamps from a {type(source).__name__}")
        for tt in by_id.values():
            self.types.setdefault(tt.topic, tt)
        out: dict[int, StampAt] = {}
        for i, tt in by_id.items():
            if not tt.stamped:
                continue
            if tt.stamp_offset is None:
                raise NoIndex(f"{tt.topic}: no fixed offset of header.stamp in the recorded definitions")
            out[i] = StampAt(tt.topic, tt.stamp_offset, tt.encoding == "cdr")
        return out

    def stamps(self, acc: Accumulator) -> Stamps:
        """``acc``'s stamps, with every stamped topic (none read: empty arrays)."""
        out = acc.stamps()
        for topic, tt in self.types.items():
            if tt.stamped and topic not in out:
                out[topic] = (np.empty(0, np.int64), np.empty(0, np.int64))
        return out


def read_with_stamps(path: Path, *, stamped_only: bool = False) -> tuple[Accumulator, str, Finder]:
    """One index pass over the recording ``path`` (what ``read_recording`` reads on its fast
    path) gathering the header stamps too: (its accumulator, the format to build it with,
    the finder with every topic's type; :meth:`Finder.stamps`). ``stamped_only``: touch only
    the chunks holding stamped messages (the accumulator's statistics are then partial).
    Raises NoIndex/Damaged/InputError/Undecodable when the fast path cannot read it: the
    caller reads it the other way."""
    from perfros_bag.ingest import detect_format, rosbag2

    finder = Finder()
    if path.is_dir():
        acc, fmt = rosbag2.read_dir(path, True, finder)
        return acc, fmt, finder
    fmt = detect_format(path)
    if fmt == "rosbag2-sqlite3":
        return rosbag2.read_sqlite(path, True, False, finder), fmt, finder
    if fmt not in ("ros1", "mcap"):
        raise Undecodable("message contents are read from .bag and .mcap files and rosbag2 directories")
    with rosbag2.open_mmap(path) as mm:
        if fmt == "ros1":
            index = rosbag1.read_index(mm)
            wanted = finder(index)
            if stamped_only:
                index = index.select([i for i, c in enumerate(index.chunks)
                                      if wanted.keys() & c.connection_counts.keys()])
            return rosbag1.read_chunks(mm, index, wanted), fmt, finder
        if not stamped_only:
            return mcapfile.read_fast(mm, stamps=finder), fmt, finder
        summary = mcapfile.read_summary(mm)
        wanted = finder(summary)
        summary = summary.select([i for i, ci in enumerate(summary.chunk_indexes)
                                  if wanted.keys() & ci.message_index_offsets.keys()])
        return mcapfile.read_chunks(mm, summary, None, wanted), fmt, finder
