"""Large recordings split by chunk ranges: any grouping of chunks merges to the whole-file stats.

Checked against ``read_recording`` on the whole file (every field, every timestamp) and
against the generator's own ground truth, on generated ROS 1 bags and MCAP files with many
chunks (every compression) and on the real recordings that have chunks; and, at the end, on
the recordings where the split path once drifted from the whole-file readers, also against
the ``mcap`` package or rosbags' AnyReader.
"""

from __future__ import annotations

import functools
import pickle
import shutil
import struct
from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.characterisation.cluster import read_split
from perfros_bag.errors import InputError
from perfros_bag.ingest import read_recording, rosbag1
from perfros_bag.ingest.split import Part, merge_parts, plan_split, read_part
from perfros_bag.ingest.stats import RecordingStats
from tests.bench.gen_corpus import TopicSpec, Truth, default_topics, write_recording
from tests.conftest import REALBAGS, assert_same_stats
from tests.ingest_gen import (
    Msg,
    anyreader_decode,
    by_topic,
    expected,
    mcap_library_decode,
    write_mcap,
    write_ros1,
    write_rosbag2,
)

GENERATED = [("ros1", "none"), ("ros1", "lz4"), ("ros1", "bz2"),
             ("mcap", "none"), ("mcap", "zstd"), ("mcap", "lz4")]
REAL_CHUNKED = ["robot_localization_test1.bag", "event_camera_test_events_1.bag",
                "rosbagjs_example-bz2.bag", "lichtblick_example.mcap"]


assert_same = assert_same_stats


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, dict[str, Truth]]]:
    root = tmp_path_factory.mktemp("split")
    topics = [*default_topics(0.02), TopicSpec("/rare", 0.5, 40, "/rare_node")]
    files = {}
    for k, (fmt, comp) in enumerate(GENERATED):
        path = root / f"{fmt}_{comp}.{'bag' if fmt == 'ros1' else 'mcap'}"
        truth = write_recording(path, fmt, topics, 6.0, chunk_bytes=6000, compression=comp, seed=k)
        files[f"{fmt}_{comp}"] = (path, truth)
    return files


def groupings(draw: st.DrawFn, n: int) -> list[list[int]]:
    """Any partition of chunks 0..n-1 into groups (not necessarily contiguous)."""
    k = draw(st.integers(1, max(1, min(n, 12))))
    label = draw(st.lists(st.integers(0, k - 1), min_size=n, max_size=n))
    return [[i for i in range(n) if label[i] == g] for g in range(k)]


@st.composite
def grouping_case(draw: st.DrawFn) -> tuple[str, list[list[int]] | int]:
    name = draw(st.sampled_from([f"{f}_{c}" for f, c in GENERATED]))
    return name, draw(st.integers(0, 2**31))


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_any_grouping_of_generated_chunks_merges_to_the_whole(
        generated: dict[str, tuple[Path, dict[str, Truth]]], data: st.DataObject) -> None:
    name = data.draw(st.sampled_from(sorted(generated)))
    path, truth = generated[name]
    plan = plan_split(path)
    assert plan.format == name.split("_")[0] and len(plan.chunks) >= 40  # really many chunks
    groups = data.draw(st.composite(lambda draw: groupings(draw, len(plan.chunks)))())
    parts = plan.parts_of(groups)
    results = [read_part(pickle.loads(pickle.dumps(p))) for p in parts]  # as shipped to a worker
    merged = merge_parts(plan, results)
    assert_same(merged, read_recording(path))
    for topic, t in truth.items():  # and the generator's ground truth
        got = merged.topics[topic]
        assert (got.messages, got.bytes) == (t.messages, t.bytes)
        assert got.times_ns.tolist() == sorted(t.times)


@functools.cache
def whole_real(name: str) -> RecordingStats:
    return read_recording(REALBAGS / name)


@pytest.mark.parametrize("name", REAL_CHUNKED)
def test_real_recordings_split_per_chunk_and_by_size(name: str) -> None:
    path = REALBAGS / name
    plan = plan_split(path)
    assert plan.format in ("ros1", "mcap") and len(plan.chunks) >= 1
    whole = whole_real(name)
    for parts in (plan.parts(1), plan.parts_of([list(range(len(plan.chunks)))[::-1]])):
        assert_same(merge_parts(plan, [read_part(p) for p in parts]), whole)
    assert len(plan.parts(1)) == len(plan.chunks)  # one chunk per task at the smallest target


@settings(max_examples=5, deadline=None)
@given(data=st.data())
def test_real_bag_any_grouping(data: st.DataObject) -> None:
    name = "robot_localization_test1.bag"  # 10 bz2 chunks
    plan = plan_split(REALBAGS / name)
    groups = data.draw(st.composite(lambda draw: groupings(draw, len(plan.chunks)))())
    assert_same(merge_parts(plan, [read_part(p) for p in plan.parts_of(groups)]), whole_real(name))


def test_parts_cover_the_file_in_target_sized_groups(
        generated: dict[str, tuple[Path, dict[str, Truth]]]) -> None:
    path, _ = generated["ros1_none"]
    plan = plan_split(path)
    parts = plan.parts(50_000)
    assert [c for p in parts for c in p.chunks] == list(plan.chunks)  # in order, each once
    assert 1 < len(parts) < len(plan.chunks)
    size = dict(zip([c.chunk_pos for c in plan.chunks], plan.sizes, strict=True))
    for p in parts[:-1]:
        total = sum(size[c.chunk_pos] for c in p.chunks)
        assert total <= 50_000 or len(p.chunks) == 1
    with pytest.raises(ValueError, match="exactly once"):
        plan.parts_of([[0, 1], [1]])


def test_read_split_in_process_equals_read_recording(
        generated: dict[str, tuple[Path, dict[str, Truth]]]) -> None:
    for name in ("ros1_lz4", "mcap_zstd"):
        path, _ = generated[name]
        assert_same(read_split(path, target_bytes=30_000), read_recording(path))


@pytest.mark.parametrize("name", ["plotjuggler_rosbag2_test", "rosbag2_mcap_talker",
                                  "mcap_conformance_TenMessages.mcap", "rosbagjs_no-messages.bag"])
def test_unsplittable_recordings_are_one_whole_task(name: str) -> None:
    # rosbag2 directories, unchunked MCAP, a bag without chunks: read_recording as one task
    path = REALBAGS / name
    plan = plan_split(path)
    assert plan.format == "whole" and plan.parts() == [Part(path, "whole")]
    assert_same(read_split(path), read_recording(path))


@pytest.mark.parametrize("name", ["rosbagjs_empty-file.bag", "webviz_invalid.bag", "rosbag-rs_dummy.bag"])
def test_broken_recordings_give_the_readers_error(name: str) -> None:
    path = REALBAGS / name
    with pytest.raises(InputError) as whole:
        read_recording(path)
    with pytest.raises(InputError) as split:
        read_split(path)  # in-process: the reader's own exception
    assert str(split.value) == str(whole.value)


def test_damaged_chunk_index_falls_back_to_the_whole_file(
        generated: dict[str, tuple[Path, dict[str, Truth]]], tmp_path: Path) -> None:
    # Break one index-data record after a chunk (its count): that part cannot be read from
    # the index, so the merge reads the whole file, as read_recording falls back to streaming.
    src, truth = generated["ros1_none"]
    path = tmp_path / "damaged.bag"
    shutil.copy(src, path)
    plan = plan_split(path)
    chunk_pos = plan.chunks[5].chunk_pos
    raw = bytearray(path.read_bytes())
    idx = raw.index(b"op=\x04", chunk_pos)  # first index-data record after that chunk
    cnt = raw.index(b"count=", idx - 64) + len(b"count=")
    raw[cnt:cnt + 4] = (10**6).to_bytes(4, "little")
    path.write_bytes(bytes(raw))
    plan = plan_split(path)
    parts = plan.parts_of([[i] for i in range(len(plan.chunks))])
    results = [read_part(p) for p in parts]
    assert results[5] is None and all(r is not None for i, r in enumerate(results) if i != 5)
    merged = merge_parts(plan, results)
    assert_same(merged, read_recording(path))
    assert merged.method == "stream"
    assert {t: (s.messages, s.bytes) for t, s in merged.topics.items()} == \
           {t: (v.messages, v.bytes) for t, v in truth.items()}


# ---------------------------------------------------------------------------------------------
# Where the split readers once drifted from the whole-file readers (issue 13): each recording
# below made the old split path disagree with read_recording. Both now use one index reader
# per format (rosbag1.read_index/read_chunks, mcapfile.read_summary/read_chunks); each case is
# checked against the whole-file read and against an independent decode.

T0 = 1_700_000_000_000_000_000


def split_per_chunk(path: Path) -> RecordingStats:
    """``path`` split into one task per chunk (at least two chunks), merged."""
    plan = plan_split(path)
    assert plan.format in ("ros1", "mcap") and len(plan.chunks) >= 2
    return merge_parts(plan, [read_part(p) for p in plan.parts(1)])


def test_log_times_up_to_the_int64_limit_are_read_from_the_index(tmp_path: Path) -> None:
    # The whole-file reader rejected index entries >= 2**62 (log times included) and streamed;
    # the split reader took log times up to 2**63 from the index. Now both read log times up
    # to 2**63 - 1 (the largest int64) from the index, and bound offsets by the chunk.
    times = [2**62 - 5, 2**62, *(2**62 + k * 7_919_000_000 for k in range(1, 400)), 2**63 - 1]
    msgs = [Msg(f"/t{k % 3}", "std_msgs/msg/String", t, bytes(10 + k % 13)) for k, t in enumerate(times)]
    path = write_mcap(tmp_path / "late.mcap", msgs, compression="zstd", chunk_size=2000)
    whole = read_recording(path)
    assert whole.method == "index"
    assert_same(split_per_chunk(path), whole)
    assert by_topic(whole) == mcap_library_decode(path)
    # one log time past int64: neither path can hold it; both give the reader's one error
    path = write_mcap(tmp_path / "beyond.mcap", [*msgs, Msg("/t0", "std_msgs/msg/String", 2**63, b"x")],
                      compression="zstd", chunk_size=2000)
    with pytest.raises(InputError) as by_whole:
        read_recording(path)
    with pytest.raises(InputError) as by_split:
        split_per_chunk(path)
    assert str(by_split.value) == str(by_whole.value)


def test_an_index_entry_listed_twice_in_a_one_channel_chunk_is_not_counted_twice(tmp_path: Path) -> None:
    # The split reader checked that indexed message records do not overlap only across
    # channels: a chunk of one channel whose message index lists a message twice counted it
    # twice (no Statistics record to disagree). The whole-file reader streams such a file.
    from mcap.writer import CompressionType, Writer

    path = tmp_path / "dup.mcap"
    with path.open("wb") as f:
        w = Writer(f, chunk_size=2000, compression=CompressionType.NONE, use_statistics=False)
        w.start(profile="", library="perfros-bag tests")
        cid = w.register_channel(topic="/a", message_encoding="json",
                                 schema_id=w.register_schema(name="s", encoding="jsonschema", data=b"{}"))
        for k in range(200):
            w.add_message(cid, log_time=T0 + k * 10**6, data=bytes(30 + k % 5), publish_time=0)
        index = w._Writer__chunk_builder.message_indices[cid]  # type: ignore[attr-defined]
        index.records.append(index.records[-1])  # the open (last) chunk lists its last message twice
        w.finish()
    whole = read_recording(path)
    assert whole.method == "stream"
    assert_same(split_per_chunk(path), whole)
    assert by_topic(whole) == mcap_library_decode(path)


@pytest.mark.parametrize("chunk_compression", ["", "lz4"])
def test_message_compressed_chunks_read_as_split_parts_equal_the_whole_recording(
        tmp_path: Path, chunk_compression: str) -> None:
    # rosbag2 message compression (every payload a zstd frame; some frames without their
    # content size): the payload size is the decompressed size. The old split reader had no
    # per-message zstd; the chunk-range reader is now the whole-file reader's own.
    import zstandard

    from perfros_bag.ingest import mcapfile
    from perfros_bag.ingest.rosbag2 import open_mmap

    msgs = [Msg(f"/t{k % 2}", "std_msgs/msg/String", T0 + k * 10**6, bytes(range(k % 200)) * 3)
            for k in range(600)]
    root = write_rosbag2(tmp_path / "rec", msgs, "mcap", compression="message")  # metadata.yaml
    storage = next(root.glob("*.mcap"))
    with_size, without_size = zstandard.ZstdCompressor(), zstandard.ZstdCompressor(write_content_size=False)
    compressed = [replace(m, payload=(with_size if k % 3 else without_size).compress(m.payload))
                  for k, m in enumerate(msgs)]
    write_mcap(storage, compressed, compression=chunk_compression, chunk_size=4000)  # many chunks
    whole = read_recording(root)
    assert whole.method == "index" and whole.format == "rosbag2-mcap"
    plan = plan_split(storage)
    assert plan.format == "mcap" and len(plan.chunks) >= 10
    with open_mmap(storage) as mm:
        parts = [mcapfile.read_chunks(mm, p.index, message_zstd=True).build(storage, "mcap")
                 for p in plan.parts_of([[i] for i in range(len(plan.chunks))][::-1])
                 if isinstance(p.index, mcapfile.Summary)]
    merged = merge_parts(plan, parts)
    assert merged.method == "index" and by_topic(merged) == by_topic(whole)
    want = expected(msgs)
    assert by_topic(whole) == {t: (e.count, e.nbytes, e.times) for t, e in want.items()}
    assert by_topic(whole) == anyreader_decode(root)


@pytest.mark.parametrize("messages", [0, 500])
@pytest.mark.parametrize("past_end", [None, 0, 1, 1000])
def test_ros1_index_position_at_and_past_the_end_of_the_file(
        tmp_path: Path, messages: int, past_end: int | None) -> None:
    # The whole-file reader took a bag header whose index position lies past the end of the
    # file as an empty index when it declares no connection and no chunk; the split planner
    # rejected any index position at or past the end. Now both read an index that ends the
    # file (an empty bag) and stream a bag whose index position is past the end.
    msgs = [Msg(f"/t{k % 2}", "std_msgs/msg/String", T0 + k * 10**6, bytes(40 + k % 9)) for k in range(messages)]
    path = write_ros1(tmp_path / "b.bag", msgs, chunk_threshold=5000)
    raw = bytearray(path.read_bytes())
    field_at = raw.index(b"index_pos=") + len(b"index_pos=")
    written = struct.unpack_from("<Q", raw, field_at)[0]
    assert (written == len(raw)) == (messages == 0)  # an empty bag's index ends the file
    if past_end is not None:  # None: as written
        struct.pack_into("<Q", raw, field_at, len(raw) + past_end)
        path.write_bytes(bytes(raw))
    indexed = past_end is None or (messages == 0 and past_end == 0)
    whole = read_recording(path)
    assert whole.method == ("index" if indexed else "stream")
    plan = plan_split(path)
    assert (plan.format == "ros1") == (indexed and messages > 0)
    assert_same(merge_parts(plan, [read_part(p) for p in plan.parts(1)]), whole)
    want = expected(msgs, ros1=True)
    assert by_topic(whole) == {t: (e.count, e.nbytes, e.times) for t, e in want.items()}
    if indexed:  # rosbags reads bags whose index is where the header says
        assert by_topic(whole) == anyreader_decode(path)


# --------------------------------------------------------------------------- header stamps


def _stamp_cases(tmp: Path) -> dict[str, Path]:
    from tests.contents_gen import sent_messages, write_mcap, write_ros1

    sent = sent_messages(600)
    return {"ros1": write_ros1(tmp / "a.bag", sent), "ros1-bz2": write_ros1(tmp / "b.bag", sent, "bz2"),
            "mcap-zstd-some-big-endian": write_mcap(tmp / "c.mcap", sent, big_endian_every=7),
            "mcap-lz4": write_mcap(tmp / "d.mcap", sent, compression="lz4")}


@pytest.fixture(scope="module")
def stamped(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return _stamp_cases(tmp_path_factory.mktemp("split-stamps"))


def _assert_latency_of_parts(path: Path, parts: list[Part]) -> None:
    """Parts' stamps, merged, == the whole file's (and the libraries'); their latencies and
    statistics == read_latency / read_recording on the whole file."""
    from perfros_bag.ingest.contents import latencies, library_stamps, read_latency
    from perfros_bag.ingest.split import merge_stamps, read_part_stamps

    results = [read_part_stamps(pickle.loads(pickle.dumps(p))) for p in parts]  # as shipped to a worker
    assert all(r is not None for r in results)
    done = [r for r in results if r is not None]
    types = {t: tt for r in done for t, tt in r[2].items()}
    merged = merge_stamps([r[1] for r in done])
    library = library_stamps(path)
    assert sorted(merged) == sorted(library)
    for topic, (times, stamps) in library.items():
        got = sorted(zip(*(a.tolist() for a in merged[topic]), strict=True))
        assert got == sorted(zip(times.tolist(), stamps.tolist(), strict=True)), topic
    assert latencies(path, merged, types) == read_latency(path)
    assert_same(merge_parts(plan_split(path), [r[0] for r in done]), read_recording(path))


@pytest.mark.parametrize("kind", ["ros1", "ros1-bz2", "mcap-zstd-some-big-endian", "mcap-lz4"])
def test_parts_stamps_merge_to_the_whole_files_latency(stamped: dict[str, Path], kind: str) -> None:
    path = stamped[kind]
    plan = plan_split(path)
    n = len(plan.chunks)
    assert n >= 4
    _assert_latency_of_parts(path, plan.parts(1))  # a chunk per part
    _assert_latency_of_parts(path, plan.parts_of([list(range(0, n, 3)), [i for i in range(n) if i % 3]]))


@pytest.mark.parametrize("name", ["robot_localization_test1.bag", "lichtblick_example.mcap"])
def test_real_recordings_parts_stamps_merge_to_the_whole(name: str) -> None:
    import warnings

    from perfros_bag.errors import PerfrosWarning

    path = REALBAGS / name
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", PerfrosWarning)
        _assert_latency_of_parts(path, plan_split(path).parts(1))


def test_a_whole_or_damaged_part_has_no_stamps(stamped: dict[str, Path]) -> None:
    from perfros_bag.ingest.split import read_part_stamps

    path = stamped["ros1"]
    assert read_part_stamps(Part(path, "whole")) is None
    plan = plan_split(path)
    part = plan.parts(1)[0]
    assert isinstance(part.index, rosbag1.BagIndex)
    bad = Part(path, "ros1", replace(part.index, chunks=(replace(part.index.chunks[0], chunk_pos=1),)))
    assert read_part_stamps(bad) is None
