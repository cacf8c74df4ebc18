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
from tests.ingest_gen import Msg, by_topic, expected, mcap_library_decode, write_mcap

T0 = 1_700_000_000_000_000_000


def _msgs() -> list[Msg]:
    """/a throughout; /b first appears in the middle of the (single) chunk."""
    out = [Msg("/a", "std_msgs/msg/String", T0 + i * 1000, bytes(100 + i)) for i in range(10)]
    out += [Msg("/b", "std_msgs/msg/String", T0 + 20_000 + i, bytes(7 + 3 * i)) for i in range(5)]
    out += [Msg("/a", "std_msgs/msg/String", T0 + 30_000 + i, bytes(50)) for i in range(3)]
    return out


def _chunk_records(path: Path) -> list[tuple[int, int, int]]:
    """(opcode, offset, record length incl. 9-byte header) of every record of every chunk,
    the chunks found and decompressed by the ``mcap`` package's stream reader."""
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader, get_chunk_data_stream

    out = []
    with path.open("rb") as f:
        for record in StreamReader(f, emit_chunks=True).records:
            if not isinstance(record, Chunk):
                continue
            stream, size = get_chunk_data_stream(record)
            while stream.count < size:
                pos, op, length = stream.count, stream.read1(), stream.read8()
                stream.read(length)
                out.append((op, pos, 9 + length))
    return out


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_fast_path_exact_with_channel_records_inside_chunk(tmp_path: Path, compression: str) -> None:
    msgs = _msgs()
    path = write_mcap(tmp_path / "c.mcap", msgs, compression=compression, chunk_size=1 << 20)
    records = _chunk_records(path)
    with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
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


def test_empty_message_index_of_a_channel_in_a_chunk(tmp_path: Path) -> None:
    # A writer may list a channel's message index with no entries after a chunk (the spec
    # does not forbid it): the fast path must sum the other channels' payload sizes per
    # channel without tripping over the empty one (it used to fail with an IndexError when
    # the empty index came last).
    from mcap.records import MessageIndex
    from mcap.writer import CompressionType, Writer

    from perfros_bag.ingest import read_recording
    from perfros_bag.ingest.split import merge_parts, plan_split, read_part

    path = tmp_path / "empty_index.mcap"
    with path.open("wb") as f:
        w = Writer(f, chunk_size=1500, compression=CompressionType.ZSTD)
        w.start(profile="", library="perfros-bag tests")
        sid = w.register_schema(name="s", encoding="jsonschema", data=b"{}")
        a = w.register_channel(topic="/a", message_encoding="json", schema_id=sid)
        b = w.register_channel(topic="/b", message_encoding="json", schema_id=sid)
        for k in range(100):
            w.add_message(a, log_time=T0 + k * 10**6, data=bytes(20 + k % 7), publish_time=0)
        w._Writer__chunk_builder.message_indices[b] = MessageIndex(channel_id=b, records=[])  # type: ignore[attr-defined]
        w.finish()
    with path.open("rb") as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as mm:
        assert any(b in ci.message_index_offsets and a in ci.message_index_offsets
                   for ci in mcapfile.read_summary(mm).chunk_indexes)  # the premise
    whole = read_recording(path)
    assert whole.method == "index"
    assert by_topic(whole) == {**mcap_library_decode(path), "/b": (0, 0, [])}
    plan = plan_split(path)
    assert len(plan.chunks) >= 2
    assert by_topic(merge_parts(plan, [read_part(p) for p in plan.parts(1)])) == by_topic(whole)
