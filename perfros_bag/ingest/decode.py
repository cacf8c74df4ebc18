"""Message contents decoded by the recording libraries (rosbags, mcap): never by our code.

* ROS 1 bags and rosbag2 sqlite3 (or compressed) directories with a ``metadata.yaml``:
  rosbags' ``AnyReader``, whose
  typestore is built from the definitions stored in the recording itself (ROS 1 connection
  records, rosbag2 ``message_definitions`` / MCAP schemas); a rosbag2 recording that stores no
  definition at all (older sqlite3 bags) falls back to rosbags' standard ROS 2 typestore, so
  standard types decode and custom ones are reported as undecodable.
* plain MCAP files (and the storage files of rosbag2 MCAP directories): the
  ``mcap`` reader for the records, a rosbags typestore built from the file's schemas
  (``ros2msg``, ``ros2idl``, ``ros1msg``) for ``cdr`` and ``ros1`` payloads, ``json.loads``
  for ``json`` payloads.

Only the requested topics are read: both libraries use the recording's indexes to touch
only the chunks (or sqlite rows) holding them. Anything that cannot be decoded raises
:class:`Undecodable` with the reason; callers turn it into one warning per topic.
"""

from __future__ import annotations

import json
from collections.abc import Collection, Iterable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

HEADER_TYPE = "std_msgs/msg/Header"
IDL_SEPARATOR = "=" * 80 + "\n"


class Undecodable(Exception):  # noqa: N818 - a reason, turned into a warning by the callers
    """The contents of a recording (or of one of its topics) cannot be decoded: why."""


@dataclass(frozen=True)
class TopicType:
    """What the recording says about one topic's messages: its type (ROS 2 spelling), the
    payload encoding (``ros1``, ``cdr``, ``json``, ...) and whether its type starts with a
    ``std_msgs/Header`` (None: no definition to tell)."""

    topic: str
    msgtype: str
    encoding: str
    stamped: bool | None
    #: where ``header.stamp`` starts in the payload (what the fast path reads), when the
    #: recorded Header has only fixed-size fields before it; None otherwise
    stamp_offset: int | None = None


def starts_with_header(typestore: Typestore, msgtype: str) -> bool | None:
    """Whether ``msgtype``'s first field is a ``std_msgs/Header`` (None: type unknown)."""
    from rosbags.typesys.base import Nodetype

    fielddefs = typestore.fielddefs.get(msgtype)
    if fielddefs is None:
        return None
    fields = fielddefs[1]
    if not fields:
        return False
    _name, (kind, ref) = fields[0]
    return bool(kind == Nodetype.NAME and ref == HEADER_TYPE)


_FIXED_SIZES = {"bool": 1, "byte": 1, "char": 1, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2,
                "int32": 4, "uint32": 4, "int64": 8, "uint64": 8, "float32": 4, "float64": 8}


def stamp_offset(typestore: Typestore, encoding: str) -> int | None:
    """Byte offset of ``header.stamp`` in a payload of a type that starts with the recorded
    ``std_msgs/Header``: ROS 1 after Header's leading fixed-size fields (``uint32 seq`` in
    ROS 1's Header), CDR after the 4-byte encapsulation when ``stamp`` is Header's first
    field. None when the recorded definitions give no fixed offset (the libraries decode)."""
    from rosbags.typesys.base import Nodetype

    header = typestore.fielddefs.get(HEADER_TYPE)
    time = typestore.fielddefs.get("builtin_interfaces/msg/Time")
    if header is None or time is None or [f[0] for f in time[1]] != ["sec", "nanosec"]:
        return None
    offset = 0
    for name, (kind, ref) in header[1]:
        if name == "stamp":
            if ref != "builtin_interfaces/msg/Time":
                return None
            if encoding == "cdr":
                return 4 if offset == 0 else None
            return offset if encoding == "ros1" else None
        if kind != Nodetype.BASE or ref[0] not in _FIXED_SIZES:
            return None
        offset += _FIXED_SIZES[ref[0]]
    return None


def topic_type(typestore: Typestore, topic: str, msgtype: str, encoding: str) -> TopicType:
    """``topic``'s :class:`TopicType` from a typestore built from the recording."""
    stamped = starts_with_header(typestore, msgtype)
    offset = stamp_offset(typestore, encoding) if stamped else None
    return TopicType(topic, msgtype, encoding, stamped, offset)


def standard_typestore() -> Typestore:
    """rosbags' standard ROS 2 types: for rosbag2 recordings that store no definition."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.LATEST)


# --------------------------------------------------------------------------- rosbags AnyReader


def anyreader_usable(path: Path) -> bool:
    """ROS 1 bags, and rosbag2 directories with metadata whose storage is sqlite3 or that
    are compressed; MCAP storage goes to the mcap reader (rosbags' own MCAP storage reader
    yields no message at all for some valid files, e.g. shared/realbags/rosbag2_mcap_talker)."""
    if path.is_file():
        return path.suffix == ".bag"
    meta = path / "metadata.yaml"
    if not meta.is_file():
        return False
    if any(p.suffix in (".db3", ".zstd") for p in path.iterdir()):
        return True
    from perfros_bag.ingest.rosbag2 import parse_metadata

    return parse_metadata(meta).compression_mode in ("FILE", "MESSAGE")


@contextmanager
def _any_reader(path: Path) -> Iterator[Any]:
    from rosbags.highlevel import AnyReader

    try:
        reader = AnyReader([path], default_typestore=standard_typestore())
        reader.open()
    except Exception as exc:  # rosbags' own errors, or what a damaged file makes it raise
        raise Undecodable(f"rosbags cannot open it: {exc}") from None
    try:
        yield reader
    finally:
        reader.close()


def _anyreader_types(reader: Any) -> dict[str, TopicType]:
    out: dict[str, TopicType] = {}
    for conn in reader.connections:
        encoding = "cdr" if reader.is2 else "ros1"
        out.setdefault(conn.topic, topic_type(reader.typestore, conn.topic, conn.msgtype, encoding))
    return out


def _anyreader_messages(reader: Any, topics: Collection[str]) -> Iterator[tuple[str, int, Any]]:
    conns = [c for c in reader.connections if c.topic in topics]
    if not conns:
        return
    for conn, log_ns, raw in reader.messages(connections=conns):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
        except Exception as exc:
            raise Undecodable(f"{conn.topic}: rosbags cannot deserialise a {conn.msgtype}: {exc}") from None
        yield conn.topic, int(log_ns), msg


# --------------------------------------------------------------------------- mcap reader


def typestore_from_definitions(definitions: Iterable[tuple[str, str, str]]) -> Typestore:
    """A rosbags typestore of the ``(type name, encoding, text)`` definitions stored in a
    recording (MCAP schemas, rosbag2's ``message_definitions``): ``ros2msg``/``ros1msg``
    (with their ``MSG:`` sub-definitions) and ``ros2idl``; a definition rosbags cannot parse
    is left out (its topics are then undecodable)."""
    from rosbags.typesys import get_types_from_idl, get_types_from_msg, get_typestore
    from rosbags.typesys.msg import normalize_msgtype
    from rosbags.typesys.stores import Stores

    typestore = get_typestore(Stores.EMPTY)
    for name, encoding, text in definitions:
        try:
            if encoding in ("ros2msg", "ros1msg"):
                typestore.register(get_types_from_msg(text, normalize_msgtype(name)))
            elif encoding == "ros2idl":  # one IDL, or several after "=" * 80 + "IDL: name" lines
                parts = text.split(IDL_SEPARATOR)[1:] if text.startswith(IDL_SEPARATOR) else [text]
                for part in parts:
                    typestore.register(get_types_from_idl(part.split("\n", 1)[1] if part.startswith("IDL: ") else part))
        except Exception:  # noqa: S112 - a definition rosbags cannot parse: its topics are undecodable
            continue
    return typestore


def channel_types(schemas: Mapping[int, tuple[str, str, str]],
                  channels: Iterable[tuple[int, str, int, str]]) -> dict[int, TopicType]:
    """Channel id -> :class:`TopicType` of an MCAP file from its schemas (id -> (name,
    encoding, text)) and channels ((id, topic, schema id, message encoding)): one rosbags
    typestore of all its schemas; ``cdr`` and ``ros1`` channels are typed from it, others
    (``json``, ...) are ``stamped`` None. Both our summary reader
    (:mod:`perfros_bag.ingest.stamps`) and the ``mcap`` reader's summary
    (:func:`mcap_types`) go through here."""
    from rosbags.typesys.msg import normalize_msgtype

    typestore = typestore_from_definitions(schemas.values())
    out: dict[int, TopicType] = {}
    for cid, topic, schema_id, encoding in channels:
        schema = schemas.get(schema_id)
        name = schema[0] if schema is not None else ""
        name = normalize_msgtype(name) if "/" in name else name
        if encoding in ("cdr", "ros1"):
            out[cid] = topic_type(typestore, topic, name, encoding)
        else:
            out[cid] = TopicType(topic, name, encoding, None)
    return out


def _library_channel_types(summary: Any) -> dict[int, TopicType]:
    """:func:`channel_types` of the ``mcap`` reader's summary."""
    schemas = {sid: (s.name, s.encoding, bytes(s.data).decode("utf-8", "replace"))
               for sid, s in summary.schemas.items()}
    return channel_types(schemas, ((cid, ch.topic, ch.schema_id, ch.message_encoding)
                                   for cid, ch in summary.channels.items()))


def mcap_reader(f: Any) -> tuple[Any, Any]:
    """The ``mcap`` reader of the open file ``f`` and its summary (which it keeps)."""
    from mcap.reader import make_reader

    try:
        reader = make_reader(f)
        summary = reader.get_summary()
    except Exception as exc:
        raise Undecodable(f"the mcap reader cannot read its summary: {exc}") from None
    if summary is None:
        raise Undecodable("MCAP file without a summary section (the mcap reader needs it to find the topics)")
    return reader, summary


def mcap_types(path: Path) -> dict[str, TopicType]:
    """Every topic's :class:`TopicType` of an MCAP file, from the ``mcap`` reader's summary."""
    with path.open("rb") as f:
        by_channel = _library_channel_types(mcap_reader(f)[1])
    out: dict[str, TopicType] = {}
    for tt in by_channel.values():
        out.setdefault(tt.topic, tt)
    return out


def _mcap_messages(path: Path, topics: Collection[str]) -> Iterator[tuple[str, int, Any]]:
    """One ``mcap`` reader: its summary (cached by the reader) gives the typestore, then the
    messages of ``topics``."""
    from rosbags.typesys.msg import normalize_msgtype

    with path.open("rb") as f:
        reader, summary = mcap_reader(f)
        typestore = typestore_from_definitions(
            (s.name, s.encoding, bytes(s.data).decode("utf-8", "replace")) for s in summary.schemas.values())
        for schema, channel, message in reader.iter_messages(topics=list(topics)):
            enc = channel.message_encoding
            try:
                if enc == "json":
                    msg: Any = json.loads(message.data)
                elif enc in ("cdr", "ros1") and schema is not None:
                    name = normalize_msgtype(schema.name)
                    if name not in typestore.fielddefs:
                        raise Undecodable(f"{channel.topic}: no usable definition of {schema.name!r} in the file")
                    msg = (typestore.deserialize_cdr(message.data, name) if enc == "cdr"
                           else typestore.deserialize_ros1(message.data, name))
                else:
                    raise Undecodable(f"{channel.topic}: no decoder for message encoding {enc!r}")
            except Undecodable:
                raise
            except Exception as exc:
                raise Undecodable(f"{channel.topic}: cannot decode a message: {exc}") from None
            yield channel.topic, int(message.log_time), msg


def mcap_files(path: Path) -> list[Path]:
    """The MCAP files read with the mcap reader: the file itself, or a rosbag2 directory's
    MCAP storage files."""
    if path.is_file():
        if path.suffix != ".mcap":
            raise Undecodable("message contents are read from .bag and .mcap files and rosbag2 directories")
        return [path]
    from perfros_bag.ingest.discover import natural_key

    files = sorted((p for p in path.iterdir() if p.is_file() and p.suffix == ".mcap"), key=natural_key)
    if not files:
        raise Undecodable("rosbag2 directory that rosbags cannot open, without .mcap storage files")
    return files


# --------------------------------------------------------------------------- entry points


def topic_types(path: Path) -> dict[str, TopicType]:
    """Every topic's :class:`TopicType`, from the definitions stored in the recording."""
    if anyreader_usable(path):
        try:
            with _any_reader(path) as reader:
                return _anyreader_types(reader)
        except Undecodable:
            if path.is_file():
                raise
    out: dict[str, TopicType] = {}
    for f in mcap_files(path):
        for topic, tt in mcap_types(f).items():
            out.setdefault(topic, tt)
    return out


def decoded_messages(path: Path, topics: Collection[str]) -> Iterator[tuple[str, int, Any]]:
    """(topic, receive/log time ns, decoded message) of every message on ``topics``, in the
    libraries' order. Typestore messages are rosbags objects; ``json`` payloads are dicts.
    Whatever the libraries raise on a damaged file becomes :class:`Undecodable`."""
    try:
        yield from _decoded_messages(path, topics)
    except Undecodable:
        raise
    except Exception as exc:  # the libraries' own errors on damaged data: a reason, never a traceback
        raise Undecodable(f"the recording library cannot read the messages: {type(exc).__name__}: {exc}") from None


def _decoded_messages(path: Path, topics: Collection[str]) -> Iterator[tuple[str, int, Any]]:
    if anyreader_usable(path):
        try:
            reader_cm = _any_reader(path)
            reader = reader_cm.__enter__()
        except Undecodable:
            if path.is_file():
                raise
        else:
            try:
                yield from _anyreader_messages(reader, topics)
            finally:
                reader_cm.__exit__(None, None, None)
            return
    for f in mcap_files(path):
        yield from _mcap_messages(f, topics)
