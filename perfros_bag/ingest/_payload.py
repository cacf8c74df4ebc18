"""Where ``header.stamp`` is in one payload, and gathering it from many payloads at once.

:mod:`perfros_bag.ingest.stamps` decides which topics are stamped and where (a
:class:`StampAt` per connection/channel); the readers gather the stamps in their own pass
with :func:`payload_stamps` (ROS 1 and CDR payloads) or :func:`cdr_head_stamps` (payload
heads as a matrix, the rosbag2 page walk).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from perfros_bag.ingest._accum import I64, U8, Damaged, NoIndex

STAMP_SIZE = 8  # builtin_interfaces/Time: sec, nanosec, 4 bytes each


@dataclass(frozen=True)
class StampAt:
    """Where ``header.stamp`` is in each payload of one connection/channel/topic id, as the
    recorded definitions say (:mod:`perfros_bag.ingest.stamps` decides): ``offset`` bytes
    into the payload; ``cdr``: a CDR payload (the stamp right after the 4-byte
    encapsulation, which gives the byte order; ``sec`` is signed), else ROS 1 (little-endian,
    unsigned)."""

    topic: str
    offset: int
    cdr: bool


#: Called by a reader with its index (a ROS 1 :class:`~perfros_bag.ingest.rosbag1.BagIndex`,
#: an MCAP :class:`~perfros_bag.ingest.mcapfile.Summary`, a rosbag2 sqlite3 connection):
#: the connection/channel/topic ids whose stamps to read in the reader's own pass, and where.
StampFinder = Callable[[Any], Mapping[int, StampAt]]


def stamp_ns(sec: I64, nsec: I64) -> I64:
    return sec * 1_000_000_000 + nsec


def pairs_u32(buf: U8, pos: I64) -> tuple[I64, I64]:
    """Two consecutive little-endian uint32 at every position ``pos`` (one 8-byte gather)."""
    if pos.size == 0:
        return pos, pos
    if int(pos.min()) < 0 or int(pos.max()) + 8 > buf.size:
        raise Damaged("stamp outside its chunk")
    pairs = np.lib.stride_tricks.sliding_window_view(buf, 8)[pos].view("<u4").astype(np.int64)
    return pairs[:, 0], pairs[:, 1]


def cdr_stamps(payload: U8, starts: I64) -> I64:
    """Stamps of CDR payloads starting at ``starts`` in ``payload`` (each at least 12 bytes,
    checked by the caller); NoIndex on an encapsulation other than plain CDR."""
    if starts.size == 0:
        return starts
    kind = (payload[starts].astype(np.int64) << 8) | payload[starts + 1].astype(np.int64)
    little = kind == 1
    if not np.all(little | (kind == 0)):
        raise NoIndex("CDR encapsulation other than plain CDR (XCDR/parameter lists)")
    sec, nsec = pairs_u32(payload, starts + 4)
    if not np.all(little):  # big-endian payloads: swap the four bytes
        big = ~little
        sec[big] = sec[big].astype(np.uint32).byteswap().astype(np.int64)
        nsec[big] = nsec[big].astype(np.uint32).byteswap().astype(np.int64)
    sec = sec.astype(np.uint32).view(np.int32).astype(np.int64)  # builtin_interfaces/Time: int32 sec
    return stamp_ns(sec, nsec)


#: the first 12 bytes of a CDR payload starting with a Header: encapsulation, options, stamp
CDR_HEAD = np.dtype([("kind", ">u2"), ("options", "<u2"), ("sec", "<u4"), ("nanosec", "<u4")])


def cdr_head_stamps(heads: U8) -> I64:
    """:func:`cdr_stamps` of payload heads given as a (rows, 12) matrix (zero-copy field
    views instead of gathers)."""
    if heads.shape[0] == 0:
        return np.empty(0, np.int64)
    rec = np.ascontiguousarray(heads).reshape(-1).view(CDR_HEAD)
    kind = rec["kind"]
    if int(kind.max()) > 1:
        raise NoIndex("CDR encapsulation other than plain CDR (XCDR/parameter lists)")
    sec, nsec = rec["sec"], rec["nanosec"]
    if int(kind.min()) == 0:  # big-endian payloads: swap the four bytes
        big = kind == 0
        sec, nsec = np.where(big, sec.byteswap(), sec), np.where(big, nsec.byteswap(), nsec)
    return stamp_ns(sec.view(np.int32).astype(np.int64), nsec.astype(np.int64))


def payload_stamps(buf: U8, starts: I64, lengths: I64, at: StampAt) -> I64:
    """The stamps of the payloads starting at ``starts`` in ``buf``, ``lengths`` bytes each;
    NoIndex when one is too short to hold its stamp (``at.offset + STAMP_SIZE``)."""
    if lengths.size and int(lengths.min()) < at.offset + STAMP_SIZE:
        raise NoIndex(f"{at.topic}: a stamped message shorter than its header")
    if at.cdr:
        if at.offset != 4:
            raise NoIndex(f"{at.topic}: header.stamp not right after the CDR encapsulation")
        return cdr_stamps(buf, starts)
    return stamp_ns(*pairs_u32(buf, starts + at.offset))
