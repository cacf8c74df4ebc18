"""``replay:`` in space.yaml: a recording stands in for launch-file nodes during a sweep.

* :func:`inspect_recording` reads the recording's index (the tool's own readers: ROS 1 bag,
  rosbag2 directory, MCAP file; nothing decoded) and decides, before anything starts, which
  topics each replaced node's player plays and the rate it stands for: the recorded
  ``(n - 1) / (t_last - t_first)`` of its fastest topic (characterisation.csv's
  ``frequency_hz``). Every problem is one :class:`InputError` line.
* :func:`prepare` writes, once, into ``DIR/.replay/`` (a cache: a resumed sweep finds it):
  the replayed topics as a ROS 1 bag (rosbags: a rosbag2 or MCAP recording is converted with
  rosbags' own message converter and typestores built from the recording's definitions, a
  ROS 1 bag copied as it is) and per replaced node a one-message *loop bag* (below). Written
  atomically (a temporary file renamed).
* :func:`player_argv` is Debian's ``rosbag play`` of both, looping, at a factor, under the
  replaced node's own name (so the master, graph.yaml and the CPU trace see that node
  publishing its topics).

**Loop restarts.** ``rosbag play -l`` starts a loop again right after the last message: the
first message of the next loop follows the last one within ~0.1-1 ms instead of one message
period (measured: a 2 s, 10 Hz recording played at x4 was recorded at 42.05 Hz instead of
40, one extra message per loop, +1/(n-1)). The loop bag holds one ``std_msgs/Empty`` on
:data:`~perfros_bag.sweep.space.LOOP_TOPIC` one mean message period after the replayed
topics' last message, so every loop lasts ``n`` periods and the restart keeps the recorded
spacing (measured: 39.996 Hz). That topic is the tool's own: never recorded, never in
graph.yaml. With several topics per replaced node the period is the one that gives no topic
a shorter gap than its own mean period.

**Time.** The players publish on wall time (``rosbag play`` without ``--clock``; no
``/use_sim_time``): the recorders and the CPU trace stay on one clock, and a loop restart
does not step time back. Messages keep their recorded ``header.stamp``, so a replayed
topic's latency (receive time - ``header.stamp``) is the age of the recording, not a
latency; nor is it for nodes that copy their input's header into their output.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import re
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from perfros_bag.errors import InputError
from perfros_bag.sweep.space import LOOP_TOPIC, Replay

#: Debian's rosbag C++ player (what the ``rosbag play`` wrapper runs).
PLAY_BIN = Path("/usr/lib/rosbag/play")
#: The folder beside the runs where converted recordings and loop bags are kept.
CACHE = ".replay"
#: A recording (its replayed topics, first to last message) must span at least this.
MIN_SPAN_S = 1.0
#: Bumped when what :func:`prepare` writes changes (old cache files are then not reused).
CACHE_VERSION = 1
#: Topics a node publishes that are not its output (ROS's logs, reconfiguration).
_NOT_OUTPUT = re.compile(r"^(rosgraph_msgs|dynamic_reconfigure)/")
_LOGS = frozenset({"/rosout", "/rosout_agg"})


@dataclass(frozen=True)
class Stand:
    """One replaced node: the topics its player plays and the rate it stands for."""

    node: str  # the ROS name, with its leading slash
    topics: tuple[str, ...]
    rate_hz: float  # the recorded rate of its fastest topic
    loop_end_ns: int  # the loop message's time: one message period after its last message

    def setting(self, factor: float) -> float:
        """Its setting in a run at ``factor``: the replayed rate in Hz (4 significant digits)."""
        return float(f"{self.rate_hz * factor:.4g}")


@dataclass(frozen=True)
class Inspected:
    """What a recording gives the replay (read before anything starts)."""

    source: Path
    stands: tuple[Stand, ...]
    types: Mapping[str, str]  # replayed topic -> message type

    @property
    def topics(self) -> tuple[str, ...]:
        return tuple(t for s in self.stands for t in s.topics)

    def settings(self, factor: float) -> dict[str, float]:
        """Each replaced node (as system.yaml names it) -> its setting at ``factor``."""
        from perfros_bag.system.names import system_node_name

        return {system_node_name(s.node): s.setting(factor) for s in self.stands}


@dataclass(frozen=True)
class Prepared:
    """The files the players play: the replayed topics as a ROS 1 bag, a loop bag per node."""

    inspected: Inspected
    bag: Path
    loops: Mapping[str, Path]  # ROS node -> its loop bag


def inspect_recording(replay: Replay) -> Inspected:
    """The replay's stands from the recording's index; an :class:`InputError` for a recording
    that does not exist or is damaged, a ``topics`` entry it does not hold, a replaced node
    with no topic in it, a topic with fewer than 2 messages, or replayed topics spanning
    less than :data:`MIN_SPAN_S`."""
    from perfros_bag.ingest import read_recording

    path = replay.recording
    if not path.exists():
        raise InputError(path, "replay: the recording does not exist")
    stats = read_recording(path)  # a damaged recording: an InputError naming it
    owners = _owners(replay, stats.topics)
    stands = []
    for node in replay.replaces:
        topics = tuple(t for t, owner in owners.items() if owner == node)
        if not topics:
            raise InputError(path, f"replay: replaced node {node} published no topic in the recording "
                             "(name them in replay.topics)")
        for t in topics:
            if stats.topics[t].messages < 2:
                raise InputError(path, f"replay: topic {t} has {stats.topics[t].messages} message(s); "
                                 "a replayed topic needs at least 2")
        chosen = [stats.topics[t] for t in topics]
        begin = min(int(t.times_ns[0]) for t in chosen)
        # the loop's end: the latest of (last message + mean period - start offset) over its topics,
        # so that on a loop restart no topic gets a gap shorter than its own mean period
        end = max(int(t.times_ns[-1]) + round((int(t.times_ns[-1]) - int(t.times_ns[0])) / (t.messages - 1))
                  - (int(t.times_ns[0]) - begin) for t in chosen)
        stands.append(Stand(node, topics, max(t.frequency_hz for t in chosen), end))
    replayed = [stats.topics[t] for s in stands for t in s.topics]
    span = (max(int(t.times_ns[-1]) for t in replayed) - min(int(t.times_ns[0]) for t in replayed)) / 1e9
    if span < MIN_SPAN_S:
        raise InputError(path, f"replay: the replayed topics span {span:.3g} s, shorter than {MIN_SPAN_S:g} s "
                         "(too short to loop at a steady rate)")
    return Inspected(path, tuple(stands), {t.topic: t.msgtype for t in replayed})


def _owners(replay: Replay, topics: Mapping[str, Any]) -> dict[str, str]:
    """Replayed topic -> the replaced node that plays it: the node that published it in the
    recording (ROS 1 ``callerid``), else the replaced node whose name is its namespace (the
    longest), else the only replaced node."""
    def owner(name: str) -> str | None:
        pubs = [p for p in topics[name].publishers if p in replay.replaces]
        if pubs:
            return str(pubs[0])
        return max((n for n in replay.replaces if name.startswith(n.rstrip("/") + "/")), key=len, default=None)

    if replay.topics is None:
        out = {}
        for name in sorted(topics):
            node = owner(name)
            if node is not None and name not in _LOGS and not _NOT_OUTPUT.match(topics[name].msgtype or ""):
                out[name] = node
        return out
    missing = [t for t in replay.topics if t not in topics]
    if missing:
        held = ", ".join(sorted(topics)) or "none"
        raise InputError(replay.recording, f"replay: topic(s) {', '.join(missing)} not in the recording "
                         f"(it holds: {held})")
    out = {}
    for name in replay.topics:
        node = owner(name) or (replay.replaces[0] if len(replay.replaces) == 1 else None)
        if node is None:
            raise InputError(replay.recording, f"replay: topic {name}: no replaced node published it (callerid) "
                             "and it is in no replaced node's namespace")
        out[name] = node
    return out


def _fingerprint(inspected: Inspected) -> str:
    """What the cached files depend on: the recording's files (path, size, mtime), the
    replayed topics and their players, the loop times and :data:`CACHE_VERSION`."""
    src = inspected.source
    files = sorted(src.rglob("*")) if src.is_dir() else [src]
    parts = [str(CACHE_VERSION), str(src)]
    for f in files:
        if f.is_file():
            st = f.stat()
            parts.append(f"{f}:{st.st_size}:{st.st_mtime_ns}")
    for s in inspected.stands:
        parts.append(f"{s.node}:{','.join(s.topics)}:{s.loop_end_ns}")
    return hashlib.sha1("\n".join(parts).encode()).hexdigest()[:12]


def prepare(inspected: Inspected, outdir: Path) -> Prepared:
    """The ROS 1 bag and the loop bags in ``outdir/.replay/``, written unless already there."""
    cache = outdir / CACHE
    cache.mkdir(parents=True, exist_ok=True)
    stem = re.sub(r"[^A-Za-z0-9._-]+", "_", inspected.source.name.removesuffix(".bag")) or "recording"
    key = _fingerprint(inspected)
    bag = cache / f"{stem}-{key}.bag"
    if not bag.exists():
        _atomically(bag, lambda tmp: convert_to_ros1(inspected, tmp))
    loops = {}
    for s in inspected.stands:
        loop = cache / f"{stem}-{key}.{s.node.strip('/').replace('/', '_')}.loop.bag"
        if not loop.exists():
            _atomically(loop, lambda tmp, s=s: _write_loop(s, tmp))
        loops[s.node] = loop
    return Prepared(inspected, bag, loops)


def _atomically(dest: Path, write: Any) -> None:
    """``write(tmp)`` a file beside ``dest``, then rename it to ``dest`` (no half-written bag
    under the cached name, whatever interrupts it)."""
    tmp = dest.with_name(f".{dest.name}.{os.getpid()}.part")
    tmp.unlink(missing_ok=True)
    try:
        write(tmp)
        tmp.replace(dest)
    finally:
        tmp.unlink(missing_ok=True)


def _write_loop(stand: Stand, dest: Path) -> None:
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    msgtype = "std_msgs/msg/Empty"
    with Writer(dest) as writer:
        conn = writer.add_connection(LOOP_TOPIC, msgtype, typestore=store, callerid=stand.node)
        writer.write(conn, stand.loop_end_ns, store.serialize_ros1(store.types[msgtype](), msgtype))


def convert_to_ros1(inspected: Inspected, dest: Path) -> None:
    """The replayed topics of the recording as a ROS 1 bag ``dest`` (each connection's
    ``callerid`` its replaced node), by rosbags: a ROS 1 bag's payloads are copied, a rosbag2
    or MCAP recording's converted with rosbags' own message converter (Header gains ROS 1's
    ``seq``) from a typestore built from the recording's own definitions. A type it cannot
    convert is an :class:`InputError` naming the type and the topic."""
    from rosbags.rosbag1 import Writer

    owner = {t: s.node for s in inspected.stands for t in s.topics}
    with Writer(dest) as writer:
        made: dict[str, tuple[Any, Any]] = {}
        for topic, msgtype, log_ns, raw, source in _raw_messages(inspected.source, list(owner)):
            if topic not in made:
                made[topic] = _connection(writer, source, topic, msgtype, owner[topic], inspected.source)
            conn, convert = made[topic]
            try:
                data = convert(raw)
            except Exception as exc:  # noqa: BLE001 - rosbags' converter on this type: name it
                raise InputError(inspected.source, f"replay: cannot convert message type {msgtype} of topic "
                                 f"{topic} to ROS 1: {exc}") from None
            writer.write(conn, log_ns, data)
    missing = [t for t in owner if t not in made]
    if missing:
        raise InputError(inspected.source, f"replay: rosbags read no message of topic(s) {', '.join(missing)}")


@dataclass
class _Source:
    """The typestore of the recording's definitions and its payload encoding."""

    typestore: Any
    is2: bool  # CDR payloads (ROS 2); False: ROS 1 payloads
    latched: frozenset[str] = frozenset()  # topics recorded as latched (ROS 2: transient local)
    destination: Any = None  # the ROS 1 typestore the converted types are registered in
    cache: Any = None


def _connection(writer: Any, source: _Source, topic: str, msgtype: str, callerid: str, path: Path) -> tuple[Any, Any]:
    """A writer connection for ``topic`` and the converter of its payloads (rosbags')."""
    from rosbags.convert.converter import generate_message_converter
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    if source.destination is None:  # as rosbags.convert does: the source's types, ROS 1's Header
        source.destination = get_typestore(Stores.EMPTY)
        source.cache = {}
        fielddefs = dict(source.typestore.fielddefs)
        if source.is2:
            fielddefs["std_msgs/msg/Header"] = get_typestore(Stores.ROS1_NOETIC).fielddefs["std_msgs/msg/Header"]
        source.destination.register(fielddefs)
    try:
        if msgtype not in source.typestore.fielddefs:
            raise KeyError("the recording holds no definition of it")
        if msgtype not in source.destination.fielddefs:
            types = get_types_from_msg(source.typestore.generate_msgdef(msgtype, ros_version=1)[0], msgtype)
            types.pop("std_msgs/msg/Header", None)
            source.destination.register(types)
        with contextlib.redirect_stdout(io.StringIO()):  # rosbags prints what it migrates
            convert = generate_message_converter(source.typestore, source.destination, msgtype, msgtype,
                                                 source.cache, src_is2=source.is2, dst_is2=False)
        conn = writer.add_connection(topic, msgtype, typestore=source.destination, callerid=callerid,
                                     latching=int(topic in source.latched))
    except Exception as exc:  # noqa: BLE001 - rosbags' typesys on a definition it cannot take
        reason = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        raise InputError(path, f"replay: cannot convert message type {msgtype} of topic {topic} to ROS 1: "
                         f"{reason}") from None
    return conn, convert


def _raw_messages(path: Path, topics: list[str]) -> Iterator[tuple[str, str, int, Any, _Source]]:
    """(topic, type, log time ns, payload, its source) of ``topics``, by the libraries the
    tool decodes with (:mod:`perfros_bag.ingest.decode`): rosbags' ``AnyReader`` for ROS 1
    bags and rosbag2 sqlite3 directories, the ``mcap`` reader for MCAP files and rosbag2
    MCAP storage. Whatever they raise on damaged data is an :class:`InputError`."""
    from perfros_bag.ingest import decode

    try:
        if decode.anyreader_usable(path):
            yield from _anyreader_raw(path, topics)
        else:
            for f in decode.mcap_files(path):
                yield from _mcap_raw(f, topics)
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - the libraries' own errors on damaged data
        raise InputError(path, f"replay: cannot read the recording's messages: {type(exc).__name__}: {exc}") from None


def _anyreader_raw(path: Path, topics: list[str]) -> Iterator[tuple[str, str, int, Any, _Source]]:
    from rosbags.highlevel import AnyReader

    from perfros_bag.ingest.decode import standard_typestore

    with AnyReader([path], default_typestore=standard_typestore()) as reader:
        conns = [c for c in reader.connections if c.topic in topics]
        source = _Source(reader.typestore, bool(reader.is2), frozenset(c.topic for c in conns if _latched(c.ext)))
        if conns:
            for conn, log_ns, raw in reader.messages(connections=conns):
                yield conn.topic, conn.msgtype, int(log_ns), raw, source


def _mcap_raw(path: Path, topics: list[str]) -> Iterator[tuple[str, str, int, Any, _Source]]:
    from rosbags.typesys.msg import normalize_msgtype

    from perfros_bag.ingest.decode import mcap_reader, typestore_from_definitions

    with path.open("rb") as f:
        reader, summary = mcap_reader(f)
        typestore = typestore_from_definitions(
            (s.name, s.encoding, bytes(s.data).decode("utf-8", "replace")) for s in summary.schemas.values())
        latched = frozenset(ch.topic for ch in summary.channels.values()
                            if _transient_local(ch.metadata.get("offered_qos_profiles", "")))
        sources = {enc: _Source(typestore, enc == "cdr", latched) for enc in ("cdr", "ros1")}
        # file order (no time-ordering heap: ~20 % of the conversion); rosbag play orders by the bag's index
        for schema, channel, message in reader.iter_messages(topics=topics, log_time_order=False):
            enc = channel.message_encoding
            name = normalize_msgtype(schema.name) if schema is not None and "/" in schema.name else ""
            if enc not in sources or not name:
                raise InputError(path, f"replay: cannot convert topic {channel.topic} (encoding {enc!r}, type "
                                 f"{name or 'unknown'}) to ROS 1: only cdr and ros1 payloads with a schema are")
            yield channel.topic, name, int(message.log_time), message.data, sources[enc]


def _latched(ext: Any) -> bool:
    """A rosbags connection recorded as latched: ROS 1 ``latching``, rosbag2 a transient-local
    QoS offer."""
    if getattr(ext, "latching", None):
        return True
    return any(getattr(getattr(q, "durability", None), "value", None) == 1
               for q in getattr(ext, "offered_qos_profiles", None) or [])


def _transient_local(profiles: str) -> bool:
    """Whether a rosbag2 MCAP channel's ``offered_qos_profiles`` (YAML text) offers transient
    local durability (ROS 2's latching)."""
    import yaml

    try:
        offers = yaml.safe_load(profiles) if profiles else None
    except yaml.YAMLError:
        return False
    return isinstance(offers, list) and any(
        isinstance(q, dict) and q.get("durability") in (1, "transient_local") for q in offers)


def player_argv(prepared: Prepared, node: str, factor: float) -> list[str]:
    """Debian's ``rosbag play`` of ``node``'s topics and its loop bag, looping, at
    ``factor`` x the recorded rate, as ROS node ``node`` (its namespace and base name)."""
    stand = next(s for s in prepared.inspected.stands if s.node == node)
    player = [str(PLAY_BIN)] if PLAY_BIN.exists() else ["rosbag", "play"]
    ns, base = node.rsplit("/", 1)
    return [*player, "--quiet", "--loop", f"--rate={factor!r}", str(prepared.bag), str(prepared.loops[node]),
            "--topics", *stand.topics, LOOP_TOPIC, f"__name:={base}", f"__ns:={ns or '/'}"]

