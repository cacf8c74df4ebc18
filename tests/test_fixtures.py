"""The bundled fixtures: regenerating them gives the committed bytes, they are small, every
format is there, and their system.yaml is the case study's instance 1."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

from perfros_bag.casestudy.instances import casestudy_system
from perfros_bag.characterisation.manifest import load_manifest
from perfros_bag.ingest import read_recording
from perfros_bag.system.systemfile import load_system

ROOT = Path(__file__).resolve().parent.parent
FIX = ROOT / "fixtures" / "recordings"
sys.path.insert(0, str(ROOT / "fixtures"))
import make_fixtures as mf  # noqa: E402


def test_regeneration_is_byte_identical(tmp_path: Path) -> None:
    mf.generate(tmp_path)
    new, old = mf.digest(tmp_path), mf.digest(FIX)
    assert set(new) == set(old)
    # system.yaml comes from the solver's case-study generator: compared by meaning below
    differ = sorted(k for k in new if new[k] != old[k] and k != "system.yaml")
    assert not differ, f"fixtures out of date, run fixtures/make_fixtures.py: {differ}"


def test_fixtures_are_small() -> None:
    total = sum(p.stat().st_size for p in FIX.rglob("*") if p.is_file())
    assert total < 2 * 1024 * 1024


def test_every_format_is_present() -> None:
    formats = {read_recording(FIX / rec.path).format for rec in mf.RECORDINGS}
    assert formats == {"ros1", "rosbag2-sqlite3", "rosbag2-mcap", "mcap"}


def test_manifest_lists_every_recording_with_its_trace() -> None:
    m = load_manifest(FIX / "manifest.yaml")
    assert m.system == FIX / "system.yaml"
    assert [e.name for e in m.recordings] == [r.path for r in mf.RECORDINGS]
    for e in m.recordings:
        assert e.path.exists() and e.cpu is not None and e.cpu.is_file()
        assert e.cpu.name == f"{e.path.name.split('.')[0]}.cpu.csv"


@pytest.mark.parametrize("rec", mf.RECORDINGS, ids=lambda r: r.path)
def test_recordings_hold_the_generated_messages(rec: mf.Recording) -> None:
    """Counts, first/last times and bytes equal what the generator wrote (reader cross-check)."""
    t0_ns = (mf.T0_S + 100 * mf.RECORDINGS.index(rec)) * 1_000_000_000
    msgs = mf.messages(rec, t0_ns)
    stats = read_recording(FIX / rec.path)
    assert set(stats.topics) == {mf.topic(n) for n in rec.nodes}
    for tp, ts in stats.topics.items():
        mine = [(t, size) for t, topic, size in msgs if topic == tp]
        assert ts.messages == len(mine)
        assert ts.first_ns == mine[0][0] and ts.last_ns == mine[-1][0]
        assert ts.bytes == sum(s for _, s in mine)


def test_system_is_instance_1_of_the_case_study() -> None:
    mine = load_system(FIX / "system.yaml")
    ref = casestudy_system(1, 1, continuous=False)
    assert [n.name for n in mine.nodes] == [n["name"] for n in ref["nodes"]]
    assert {n.name: n.topics for n in mine.nodes} == {n["name"]: tuple(n["topics"]) for n in ref["nodes"]}
    assert {c.name: c.capacity for c in mine.computers} == {c["name"]: c["capacity"] for c in ref["computers"]}
    # the solver's copy of instance 1 (fixtures/casestudy) must use the same names
    other = load_system(ROOT / "fixtures" / "casestudy" / "instance1.yaml")
    assert [n.name for n in other.nodes] == [n.name for n in mine.nodes]
    assert {c.name for c in other.computers} == {c.name for c in mine.computers}
    assert {n.name: n.topics for n in other.nodes} == {n.name: n.topics for n in mine.nodes}
