"""Large recordings split by chunk ranges: any grouping of chunks merges to the whole-file stats.

Checked against ``read_recording`` on the whole file (every field, every timestamp) and
against the generator's own ground truth, on generated ROS 1 bags and MCAP files with many
chunks (every compression) and on the real recordings that have chunks.
"""

from __future__ import annotations

import functools
import pickle
import shutil
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from perfros_bag.errors import InputError
from perfros_bag.ingest import read_recording
from perfros_bag.ingest.split import Part, merge_parts, plan_split, read_part, read_split
from perfros_bag.ingest.stats import RecordingStats
from tests.bench.gen_corpus import TopicSpec, Truth, default_topics, write_recording
from tests.conftest import REALBAGS

GENERATED = [("ros1", "none"), ("ros1", "lz4"), ("ros1", "bz2"),
             ("mcap", "none"), ("mcap", "zstd"), ("mcap", "lz4")]
REAL_CHUNKED = ["robot_localization_test1.bag", "event_camera_test_events_1.bag",
                "rosbagjs_example-bz2.bag", "lichtblick_example.mcap"]


def assert_same(a: RecordingStats, b: RecordingStats) -> None:
    assert (a.path, a.format, a.method) == (b.path, b.format, b.method)
    assert list(a.topics) == list(b.topics)
    for name, x in a.topics.items():
        y = b.topics[name]
        assert (x.topic, x.msgtype, x.messages, x.bytes, x.publishers) == \
               (y.topic, y.msgtype, y.messages, y.bytes, y.publishers), name
        assert x.times_ns.dtype == y.times_ns.dtype and np.array_equal(x.times_ns, y.times_ns), name
        assert (x.frequency_hz, x.median_rate_hz, x.p95_gap_s) == \
               (y.frequency_hz, y.median_rate_hz, y.p95_gap_s)


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
    size = dict(zip([c[0] for c in plan.chunks], plan.sizes, strict=True))
    for p in parts[:-1]:
        total = sum(size[c[0]] for c in p.chunks)
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
    chunk_pos = plan.chunks[5][0]
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
