"""End-to-end latency along system.yaml ``chains`` and the network delay a plan adds, against
brute force over rosbags' own deserialisation (AnyReader) of recordings its writers made."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
from contents_gen import CHAIN_TOPICS, chain_messages, solve_and_validate, write_chain
from typer.testing import CliRunner

from perfros_bag.cli import app
from perfros_bag.errors import InputError, PerfrosWarning
from perfros_bag.ingest.chains import read_chain_latencies
from perfros_bag.system.systemfile import parse_system
from perfros_bag.system.types import Chain

VISION = Chain("vision", ("/camera/image_raw", "/detector/circles", "/tracker/tracks"))


def _decoded(path: Path) -> dict[str, list[tuple[int, int | None, int]]]:
    """topic -> [(log time, header.stamp or None without a header, raw bytes)], by AnyReader."""
    from rosbags.highlevel import AnyReader

    out: dict[str, list[tuple[int, int | None, int]]] = {t: [] for t in CHAIN_TOPICS}
    with AnyReader([path]) as reader:
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            header = getattr(msg, "header", None)
            stamp = None if header is None else header.stamp.sec * 10**9 + header.stamp.nanosec
            out[conn.topic].append((t, stamp, len(raw)))
    return out


def _brute(decoded: dict[str, list[tuple[int, int | None, int]]], a: str, b: str, *, from_stamp: bool) -> list[float]:
    """Messages of b whose non-zero stamp is on a: b's log time minus the stamp
    (``from_stamp``) or minus the earliest log time of a's message with that stamp."""
    first: dict[int, int] = {}
    for t, s, _ in decoded[a]:
        if s:
            first[s] = min(first.get(s, t), t)
    return [(t - (s if from_stamp else first[s])) / 1e9 for t, s, _ in decoded[b] if s and s in first]


def _stats(delays: list[float]) -> tuple[int, float, float, float]:
    return len(delays), float(np.percentile(delays, 50)), float(np.percentile(delays, 95)), max(delays)


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("chains")
    return {"ros1": write_chain(d / "run.bag", "ros1"), "sqlite3": write_chain(d / "r2sql", "sqlite3"),
            "mcap": write_chain(d / "r2mcap", "mcap")}


@pytest.mark.parametrize("kind", ["ros1", "sqlite3", "mcap"])
def test_chain_latency_equals_brute_force_over_the_libraries(recordings: dict[str, Path], kind: str) -> None:
    path = recordings[kind]
    with warnings.catch_warnings():
        warnings.simplefilter("error", PerfrosWarning)
        [got] = read_chain_latencies(path, [VISION])
    decoded = _decoded(path)
    e2e = _brute(decoded, VISION.topics[0], VISION.topics[-1], from_stamp=True)
    sent = chain_messages()
    # the generator's own view: tracker outputs of camera frames (not the detector's own stamps, not 0)
    camera = {s for topic, _, s in sent if topic == "/camera/image_raw" and s}
    assert len(e2e) == sum(1 for topic, _, s in sent if topic == "/tracker/tracks" and s in camera) > 0
    assert got.messages == sum(1 for _, s, _ in decoded["/tracker/tracks"] if s)
    assert got.messages > len(e2e)  # unmatched stamps are counted, not matched
    assert got.end_to_end is not None
    assert (got.end_to_end.messages, got.end_to_end.p50_s, got.end_to_end.p95_s, got.end_to_end.max_s) == \
        pytest.approx(_stats(e2e), abs=1e-9)
    for hop, (a, b) in zip(got.hops, zip(VISION.topics, VISION.topics[1:], strict=False), strict=True):
        assert (hop.src, hop.dst) == (a, b)
        assert hop.delays is not None
        assert (hop.delays.messages, hop.delays.p50_s, hop.delays.p95_s, hop.delays.max_s) == \
            pytest.approx(_stats(_brute(decoded, a, b, from_stamp=False)), abs=1e-9)


def test_headerless_topic_and_unmatched_stamps_leave_the_chain_empty_with_one_warning(
        recordings: dict[str, Path], tmp_path: Path) -> None:
    plain = Chain("plain", ("/camera/image_raw", "/detector/plain"))
    with pytest.warns(PerfrosWarning) as record:
        [got] = read_chain_latencies(recordings["ros1"], [plain])
    msgs = [str(w.message) for w in record]
    assert len(msgs) == 1 and "chain 'plain'" in msgs[0] and "/detector/plain has no std_msgs/Header" in msgs[0]
    assert got.end_to_end is None and got.hops[0].delays is None and got.to_dict()["matched"] == 0

    # every detection with a stamp of its own: nothing downstream matches the camera
    own = [(topic, t, s + 1 if topic != "/camera/image_raw" and s else s) for topic, t, s in chain_messages()]
    path = write_chain(tmp_path / "own.bag", "ros1", own)
    with pytest.warns(PerfrosWarning) as record:
        [got] = read_chain_latencies(path, [VISION])
    assert got.end_to_end is None and got.hops[0].delays is None
    assert got.hops[1].delays is not None  # detector -> tracker still share their stamps
    msgs = [str(w.message) for w in record]  # the chain, and its first hop
    assert len(msgs) == 2
    assert "chain 'vision': no message of /tracker/tracks carries the header.stamp of a message of " \
           "/camera/image_raw: no end-to-end latency" in msgs[0]
    assert "chain 'vision': hop /camera/image_raw -> /detector/circles: no message of /detector/circles" in msgs[1]


SYSTEM = """
computers:
  - {name: robot1, kind: robot, capacity: 100}
  - {name: server, kind: server, capacity: 400}
links:
  - {between: [robot1, relay], bandwidth_kBps: 50}
  - {between: [relay, server], bandwidth_kBps: 20}
nodes:
  - {name: camera, weight: 0.5, residence: [robot1], topics: [/camera/image_raw],
     settings: [{cpu: 10, performance: 100, frequency_hz: 30.3}]}
  - {name: detector, weight: 0.25, residence: [server], topics: [/detector/circles, /detector/plain],
     settings: [{cpu: 50, performance: 100, frequency_hz: 20.2}]}
  - {name: tracker, weight: 0.25, residence: [server], topics: [/tracker/tracks],
     settings: [{cpu: 10, performance: 100, frequency_hz: 20.2}]}
edges:
  - {from: camera, to: detector, topic: /camera/image_raw}
  - {from: detector, to: tracker}
chains:
  - {name: vision, topics: [/camera/image_raw, /detector/circles, /tracker/tracks]}
"""


def _system_text() -> str:
    relay = "  - {name: relay, kind: server, capacity: 1}\n"
    return SYSTEM.replace("links:\n", relay + "links:\n", 1)


@pytest.mark.parametrize(("chains", "problem"), [
    ("[{name: v, topics: [/camera/image_raw]}]", r"chain 'v': topics: a chain needs at least 2 topics, got 1"),
    ("[{name: v, topics: [/camera/image_raw, /nope]}]", r"chain 'v': topics\[1\]: '/nope' is not a topic"),
    ("[{name: v, topics: [/camera/image_raw, /camera/image_raw]}]", r"chain 'v': topics: a topic is listed twice"),
    ("[{name: v, topics: [/camera/image_raw, /tracker/tracks], delay: 1}]", r"chains\[0\]: unknown"),
    ("[{topics: [/camera/image_raw, /tracker/tracks]}]", r"chains\[0\]: missing required field\(s\) 'name'"),
    ("{name: v}", r"chains: must be a list"),
])
def test_chain_mistakes_are_one_line_errors_naming_the_chain(chains: str, problem: str) -> None:
    import yaml

    text = _system_text().split("chains:")[0] + f"chains: {chains}\n"
    with pytest.raises(InputError, match=r"^system.yaml: " + problem) as exc:
        parse_system(yaml.safe_load(text))
    assert "\n" not in str(exc.value)


def test_validate_shows_network_delay_and_chain_latency(recordings: dict[str, Path], tmp_path: Path) -> None:
    system = tmp_path / "system.yaml"
    system.write_text(_system_text())
    res, saved = solve_and_validate(system, recordings["sqlite3"], tmp_path)
    doc = json.loads(res.stdout)
    decoded = _decoded(recordings["sqlite3"])

    # network: camera (robot1) -> detector (server) crosses both links; detector -> tracker stays on the server
    assert [(c["edge"], c["topic"]) for c in doc["network"]] == [("camera->detector", "/camera/image_raw")]
    [net] = doc["network"]
    assert net["links"] == [["robot1", "relay"], ["relay", "server"]]
    sizes = [n for _, _, n in decoded["/camera/image_raw"]]
    mean_bytes = sum(sizes) / len(sizes)
    assert net["message_bytes"] == pytest.approx(mean_bytes)
    assert net["predicted_delay_s"] == pytest.approx(mean_bytes / 50_000 + mean_bytes / 20_000)
    delays = [(t - s) / 1e9 for t, s, _ in decoded["/camera/image_raw"] if s]
    assert net["latency_p50_s"] == pytest.approx(float(np.percentile(delays, 50)), abs=1e-9)
    assert net["latency_p95_s"] == pytest.approx(float(np.percentile(delays, 95)), abs=1e-9)

    [chain] = doc["chains"]
    e2e = _stats(_brute(decoded, "/camera/image_raw", "/tracker/tracks", from_stamp=True))
    assert (chain["matched"], chain["p50_s"], chain["p95_s"], chain["max_s"]) == pytest.approx(e2e, abs=1e-9)
    assert [h["matched"] for h in chain["hops"]] == [
        len(_brute(decoded, a, b, from_stamp=False)) for a, b in zip(VISION.topics, VISION.topics[1:], strict=False)]
    assert "transfer delay per message" in res.stderr and "end-to-end latency" in res.stderr

    from perfros_bag.report.html import build_report, fmt

    page = build_report(tmp_path / "report", validation=saved).read_text()
    network = page.split('id="validation-network"', 1)[1].split("</table>", 1)[0]
    assert f">{fmt(net['predicted_delay_s'])}<" in network and f">{fmt(net['latency_p95_s'])}<" in network
    chains = page.split('id="validation-chains"', 1)[1].split("</table>", 1)[0]
    assert f">{fmt(chain['p95_s'])}<" in chains and "hop /detector/circles -&gt; /tracker/tracks" in chains


def test_validate_reads_no_stamps_without_chains_or_network(recordings: dict[str, Path], tmp_path: Path,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    import perfros_bag.ingest.contents as contents

    text = _system_text().split("chains:")[0].replace("residence: [server]", "residence: [robot1]")
    system = tmp_path / "system.yaml"
    system.write_text(text)
    plan = tmp_path / "plan.json"
    runner = CliRunner()
    assert runner.invoke(app, ["solve", str(system), "--problem", "1", "--out", str(plan)]).exit_code == 0

    def boom(*_: object, **__: object) -> None:
        raise AssertionError("stamps read")

    monkeypatch.setattr(contents, "read_contents_stamps", boom)
    res = runner.invoke(app, ["validate", str(recordings["ros1"]), str(plan), "--json", "--tolerance", "100"])
    assert res.exit_code == 0, res.output
    doc = json.loads(res.stdout)
    assert doc["network"] == [] and doc["chains"] == []


def test_info_latency_with_a_system_gives_its_chains(recordings: dict[str, Path], tmp_path: Path) -> None:
    system = tmp_path / "system.yaml"
    system.write_text(_system_text())
    runner = CliRunner()
    res = runner.invoke(app, ["info", str(recordings["mcap"]), "--latency", "--json", "--system", str(system)])
    assert res.exit_code == 0, res.output
    [chain] = json.loads(res.stdout)["chains"]
    [expected] = read_chain_latencies(recordings["mcap"], [VISION])
    assert chain == expected.to_dict()
    assert "chains" not in json.loads(runner.invoke(app, ["info", str(recordings["mcap"]), "--json"]).stdout)
    res = runner.invoke(app, ["info", str(recordings["mcap"]), "--system", str(system)])
    assert res.exit_code == 2 and "add --latency" in res.output


def test_validate_sets_each_chain_and_hop_prediction_beside_its_measurement(recordings: dict[str, Path],
                                                                           tmp_path: Path) -> None:
    text = _system_text().replace(
        "settings: [{cpu: 50, performance: 100, frequency_hz: 20.2}]}",
        "input: /camera/image_raw, settings: [{cpu: 10, cpu_per_hz: 1.3, performance: 100, out_per_in: 0.667, "
        "bytes_per_msg: 40}]}").replace(
        "settings: [{cpu: 10, performance: 100, frequency_hz: 20.2}]}",
        "input: /detector/circles, settings: [{cpu: 2, cpu_per_hz: 0.4, performance: 100, bytes_per_msg: 20}]}")
    text = text.replace("topics: [/camera/image_raw, /detector/circles, /tracker/tracks]}",
                        "topics: [/camera/image_raw, /detector/circles, /tracker/tracks], budget_ms: {p95: 900}}")
    system = tmp_path / "system.yaml"
    system.write_text(text)
    res, saved = solve_and_validate(system, recordings["ros1"], tmp_path)
    plan = json.loads((tmp_path / "plan.json").read_text())
    [planned] = plan["chains"]
    [chain] = json.loads(saved.read_text())["chains"]
    assert planned["predicted_ms"]["p95"] <= 900
    assert chain["predicted_ms"] == planned["predicted_ms"] and chain["budget_ms"] == {"p95": 900}
    assert chain["budget_held"] is (1000 * chain["p95_s"] <= 900)
    assert [h["predicted_ms"] for h in chain["hops"]] == [h["predicted_ms"] for h in planned["hops"]]
    assert [(h["from"], h["to"]) for h in chain["hops"]] == [(h["from"], h["to"]) for h in planned["hops"]]
    assert f"{planned['predicted_ms']['p95'] / 1000:.3g}" in res.stderr  # the table's pred p95 (s)

    # a plan that states no chains (written before they were predicted) is predicted by validate, alike
    bare = tmp_path / "bare.json"
    bare.write_text(json.dumps({k: v for k, v in plan.items() if k != "chains"}))
    again = CliRunner().invoke(app, ["validate", str(recordings["ros1"]), str(bare), "--json", "--tolerance", "100"])
    assert again.exit_code == 0, again.output
    [rechain] = json.loads(again.stdout)["chains"]
    assert rechain["predicted_ms"] == pytest.approx(planned["predicted_ms"], rel=1e-6)

    from perfros_bag.report.html import build_report, fmt

    page = build_report(tmp_path / "report", validation=saved, plan=tmp_path / "plan.json").read_text()
    rows = page.split('id="validation-chains"', 1)[1].split("</table>", 1)[0]
    assert f">{fmt(planned['predicted_ms']['p95'] / 1000)}<" in rows and "p95 900 ms" in rows
    assert f">{fmt(planned['predicted_ms']['p50'])}<" in page.split('id="plan-chains"', 1)[1].split("</table>", 1)[0]
