"""MCAP fast path on chunks that hold schema/channel records between messages.

The message indexes give only message offsets, so they cannot tell a message record that runs
to the next indexed offset from a message followed by a schema or channel record: payload sizes
must be read from each decompressed record (mcapfile.read_fast never derives them from offset
gaps). These chunks are built by the ``mcap`` writer, which writes a channel's schema and
channel records into the open chunk when the channel first appears.
"""

from __future__ import annotations

import mmap
from pathlib import Path

import pytest

from perfros_bag.ingest import mcapfile
from tests.ingest_gen import Msg, expected, write_mcap

T0 = 1_700_000_000_000_000_000


def _msgs() -> list[Msg]:
    """/a throughout; /b first appears in the middle of the (single) chunk."""
    out = [Msg("/a", "std_msgs/msg/String", T0 + i * 1000, bytes(100 + i)) for i in range(10)]
    out += [Msg("/b", "std_msgs/msg/String", T0 + 20_000 + i, bytes(7 + 3 * i)) for i in range(5)]
    out += [Msg("/a", "std_msgs/msg/String", T0 + 30_000 + i, bytes(50)) for i in range(3)]
    return out


def _chunk_records(mm: mmap.mmap) -> list[tuple[int, int, int]]:
    """(opcode, offset, record length incl. 9-byte header) of every record of every chunk."""
    st = mcapfile._State()
    chunks, _ = mcapfile._summary(mm, st)
    out = []
    for ci in chunks:
        _, start, length = mcapfile._record(mm, ci.chunk_start, len(mm))
        comp, rstart, rlen, usize = mcapfile._chunk_records(mm, start, length)
        raw = mcapfile.decompress(comp, memoryview(mm)[rstart:rstart + rlen], usize)
        pos = 0
        while pos < len(raw):
            op, cstart, clen = mcapfile._record(raw, pos, len(raw))
            out.append((op, pos, 9 + clen))
            pos = cstart + clen
    return out


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_fast_path_exact_with_channel_records_inside_chunk(tmp_path: Path, compression: str) -> None:
    msgs = _msgs()
    path = write_mcap(tmp_path / "c.mcap", msgs, compression=compression, chunk_size=1 << 20)
    with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        records = _chunk_records(mm)
        ops = [op for op, _, _ in records]
        first_msg = ops.index(mcapfile.OP_MESSAGE)
        # the premise: a channel record sits after a message, inside the chunk
        assert mcapfile.OP_CHANNEL in ops[first_msg:]
        # offset gaps would overstate the payload of the message before that channel record
        msg_offsets = [pos for op, pos, _ in records if op == mcapfile.OP_MESSAGE]
        gaps = [b - a for a, b in zip(msg_offsets, msg_offsets[1:], strict=False)]
        lengths = [n for op, _, n in records if op == mcapfile.OP_MESSAGE][:-1]
        assert any(g > n for g, n in zip(gaps, lengths, strict=True))
        acc = mcapfile.read_fast(mm)
        assert acc.method == "index"
        got = acc.build(path, "mcap")
    want = expected(msgs)
    assert {t: (s.messages, s.bytes) for t, s in got.topics.items()} == \
        {t: (e.count, e.nbytes) for t, e in want.items()}
    for t, e in want.items():
        assert got.topics[t].times_ns.tolist() == e.times
