"""Small file helpers: atomic writes (no half-written outputs) and safe YAML/JSON reads."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import yaml

from perfros_bag.errors import InputError


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


def atomic_write_json(path: str | Path, data: Any) -> None:
    atomic_write_text(path, json.dumps(data, indent=2, sort_keys=False) + "\n")


def read_text(path: str | Path, what: str = "file", *, newline: str | None = None) -> str:
    """A text file's content; a missing, unreadable or non-UTF-8 file, or a directory,
    becomes an :class:`InputError` naming it (``what`` says what was expected there)."""
    p = Path(path)
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
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise InputError(p, f"invalid YAML{where}: {problem}") from None


def read_json(path: str | Path) -> Any:
    p = Path(path)
    text = read_text(p, "JSON file")
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise InputError(p, f"invalid JSON at line {exc.lineno}, column {exc.colno}: {exc.msg}") from None
