"""Small file helpers: atomic writes (no half-written outputs), safe YAML/JSON reads, strict
JSON writes, and what kind of perfros-bag document a file is (:func:`expect_kind`)."""

from __future__ import annotations

import json
import os
import sys
import tempfile
from collections.abc import Collection, Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import yaml

from perfros_bag.errors import InputError, PerfrosError

#: The tool's own JSON documents, recognised by their ``format`` key.
DOCUMENT_KINDS: dict[str, str] = {
    "perfros-bag/plan@1": "a perfros-bag plan (plan.json)",
    "perfros-bag/model@1": "a perfros-bag model (model.json)",
    "perfros-bag/validation@1": "a perfros-bag validation (validation.json)",
    "perfros-bag/info@1": "a perfros-bag recording summary (info --json)",
    "perfros-bag/casestudy-run@1": "a perfros-bag case-study run record (run.json)",
    "perfros-bag/tune@1": "a perfros-bag tuning loop (tune.json)",
}


SYSTEM_KIND = "a system description (system.yaml)"
MANIFEST_KIND = "a manifest (manifest.yaml)"


class NonFiniteOutputError(PerfrosError):
    """A document to write holds NaN or an infinity (strict JSON cannot: a bug, or an input
    that should have been refused)."""


def document_kind(data: Any) -> str | None:
    """What ``data`` is when it is one of the tool's own documents (by its ``format`` key),
    a system.yaml, a manifest.yaml or a characterisation table; None when it is none of them."""
    if isinstance(data, Mapping):
        fmt = data.get("format")
        if isinstance(fmt, str) and fmt in DOCUMENT_KINDS:
            return DOCUMENT_KINDS[fmt]
        if isinstance(fmt, str) and fmt.startswith("perfros-bag/"):
            return f"a perfros-bag document of format {fmt!r}"
        if "computers" in data and "nodes" in data:
            return SYSTEM_KIND
        if "recordings" in data:
            return MANIFEST_KIND
    return None


def expect_kind(path: str | Path | None, data: Any, expected: str, accept: Collection[str]) -> None:
    """Raise an :class:`InputError` saying what ``data`` is and that ``expected`` was
    expected, when :func:`document_kind` recognises it as a kind not in ``accept`` (kinds:
    :data:`DOCUMENT_KINDS` values, :data:`SYSTEM_KIND`, :data:`MANIFEST_KIND`)."""
    kind = document_kind(data)
    if kind is not None and kind not in accept:
        raise InputError(path, f"this is {kind}, expected {expected}")


#: the tool's own CSV tables, recognised by how their header starts
CHARACTERISATION_KIND = "a characterisation table (characterisation.csv)"
CSV_KINDS: dict[str, str] = {"recording,node,": CHARACTERISATION_KIND}


def file_kind(path: str | Path) -> str | None:
    """What a ``.json``, ``.yaml``/``.yml`` or ``.csv`` file is when it is one of the tool's
    own files (:func:`text_kind`); None for anything else (a recording)."""
    p = Path(path)
    if p.suffix.lower() not in (".json", ".yaml", ".yml", ".csv") or not p.is_file():
        return None
    try:
        text = p.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError):
        return None
    return text_kind(text)


def text_kind(text: str) -> str | None:
    """What a file's text is when it is one of the tool's CSV tables (:data:`CSV_KINDS`),
    JSON documents or YAML systems or manifests (:func:`document_kind`), else None: for the
    message when the reader of another format is given it."""
    header = next((ln for ln in text.splitlines() if not ln.startswith("#")), "")
    csv_kind = next((kind for start, kind in CSV_KINDS.items() if header.startswith(start)), None)
    if csv_kind is not None:
        return csv_kind
    head = text.lstrip()[:1]
    try:
        if head in ("{", "["):
            data = json.loads(text)
        else:
            data = yaml.load(text, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))  # noqa: S506 - safe
    except (ValueError, RecursionError, yaml.YAMLError):
        return None
    return document_kind(data)


@contextmanager
def atomic_open(path: str | Path, mode: str = "w", encoding: str | None = "utf-8") -> Iterator[IO[Any]]:
    """Open a temporary file beside ``path``; rename it over ``path`` only on success."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    # mkstemp makes the file 0600; give the output the permissions a plain open() would.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    binary = "b" in mode
    try:
        with os.fdopen(fd, mode, encoding=None if binary else encoding) as handle:
            yield handle
        os.replace(tmp, target)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise


def atomic_write_text(path: str | Path, text: str) -> None:
    with atomic_open(path, "w") as handle:
        handle.write(text)


def append_lines(path: str | Path, text: str) -> None:
    """Append whole lines (``text`` ends with a newline) to ``path`` in one ``write`` and
    sync it: a file that grows by a record at a time (watch's windows) costs each record,
    not the whole file again. Lines already there are never touched, so a run stopped at
    any moment keeps every record it finished."""
    if text and not text.endswith("\n"):
        raise ValueError("append_lines: the text must end with a newline")
    fd = os.open(path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
    try:
        data = text.encode("utf-8")
        while data:
            data = data[os.write(fd, data):]
        os.fsync(fd)
    finally:
        os.close(fd)


def json_text(data: Any, indent: int | None = 2) -> str:
    """``data`` as strict JSON (no NaN or Infinity, which JSON parsers refuse): a
    non-finite number is a :class:`NonFiniteOutputError`, and nothing is written."""
    try:
        return json.dumps(data, indent=indent, sort_keys=False, allow_nan=False)
    except ValueError as exc:
        raise NonFiniteOutputError(f"refusing to write JSON with a non-finite number ({exc})") from None


def atomic_write_json(path: str | Path, data: Any) -> None:
    """Write ``data`` as strict JSON (:func:`json_text`), atomically."""
    atomic_write_text(path, json_text(data) + "\n")


def require_regular(path: Path, what: str) -> None:
    """An :class:`InputError` for a path that exists but is neither a regular file nor a
    directory (a named pipe, device or socket): opening a pipe blocks until someone writes,
    and a device like /dev/zero never ends; said at once instead."""
    if path.exists() and not path.is_file() and not path.is_dir():
        raise InputError(path, f"is not a regular file (a named pipe, device or socket), expected a {what}")


def read_text(path: str | Path, what: str = "file", *, newline: str | None = None) -> str:
    """A text file's content; a missing, unreadable or non-UTF-8 file, a directory, a named
    pipe or a device becomes an :class:`InputError` naming it (``what`` says what was
    expected there)."""
    p = Path(path)
    require_regular(p, what)
    try:
        with p.open(encoding="utf-8", newline=newline) as handle:
            return handle.read()
    except FileNotFoundError:
        raise InputError(p, f"{what} not found") from None
    except IsADirectoryError:
        raise InputError(p, f"is a directory, expected a {what}") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(p, f"cannot read {what}: {exc}") from None


def read_yaml(path: str | Path) -> Any:
    """Safe-load a YAML file (never constructs Python objects); any problem becomes an
    :class:`InputError` naming it."""
    p = Path(path)
    text = read_text(p, "YAML file")
    # libyaml's safe loader when built (big rosbag2 metadata: ~0.1 s in pure Python); both
    # construct plain data only.
    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
    try:
        return yaml.load(text, Loader=loader)  # noqa: S506 - a safe loader
    except RecursionError:
        raise InputError(p, "invalid YAML: nested too deeply") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise InputError(p, f"invalid YAML{where}: {problem}") from None


def kind_of(obj: Any) -> str:
    """What a parsed YAML/JSON value is, for an error message ("nothing" for null)."""
    return "nothing" if obj is None else type(obj).__name__


def unknown_keys(mapping: Mapping[Any, Any], allowed: Collection[str]) -> str | None:
    """The one wording of a YAML/JSON mapping's keys that its format does not know (None
    when every key is allowed): ``unknown key(s) 'x', 'y' (allowed: a, b)``."""
    unknown = sorted(str(k) for k in mapping if k not in allowed)
    if not unknown:
        return None
    return f"unknown key(s) {', '.join(map(repr, unknown))} (allowed: {', '.join(sorted(allowed))})"


def read_json(path: str | Path) -> Any:
    """Parse a JSON file; invalid JSON, nesting too deep for Python and integers too long
    for it (more than ``sys.get_int_max_str_digits()`` digits) are :class:`InputError`s.
    NaN, Infinity and numbers beyond a float's range parse (as non-finite floats): the
    format's reader refuses them, naming the place."""
    p = Path(path)
    text = read_text(p, "JSON file")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        kind = text_kind(text) if text.lstrip()[:1] not in ("{", "[") else None  # clearly not JSON: what is it?
        if kind is not None:
            raise InputError(p, f"this is {kind}, not a JSON document") from None
        raise InputError(p, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
    except RecursionError:
        raise InputError(p, "invalid JSON: nested too deeply") from None
    except ValueError:  # an integer with more digits than Python converts
        raise InputError(p, f"invalid JSON: an integer longer than {sys.get_int_max_str_digits()} digits") from None
