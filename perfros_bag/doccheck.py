"""One checker for the tool's input documents (system.yaml, model.json, plan.json,
space.yaml, manifest.yaml, graph.yaml): a :class:`Doc` knows the file it reads, and each
check names the place in it (``nodes[2].settings[0].cpu``) in the one-line
:class:`~perfros_bag.errors.InputError` it raises: ``<file>: <place>: <problem>``.

The wordings are each reader's contract (its bad-input tests pin them), so the few that
differ between formats are class attributes a reader's subclass sets (:attr:`Doc.container`:
"a mapping" in YAML, "an object" in JSON) or arguments. Light module: the standard library and the shared helpers only.
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from enum import Enum
from pathlib import Path
from typing import Any, TypeVar

from perfros_bag.errors import InputError
from perfros_bag.fileio import kind_of, unknown_keys
from perfros_bag.limits import MAX_MAGNITUDE, number_problem

__all__ = ["Doc"]

E = TypeVar("E", bound=Enum)


class Doc:
    """Checks on one document's parsed content, each naming the place it checks."""

    #: what :meth:`mapping` expected (``expected a mapping, got list``)
    container = "a mapping"
    #: what :meth:`items` says of a non-list (``must be a list, got dict``)
    list_wording = "must be a list"

    def __init__(self, path: str | Path | None) -> None:
        self.path = path

    def fail(self, where: str, problem: str) -> InputError:
        """``<file>: <where>: <problem>`` (without a place: ``<file>: <problem>``)."""
        return InputError(self.path, f"{where}: {problem}" if where else problem)

    def mapping(self, obj: Any, where: str, allowed: Collection[str] | None = None,
                required: Collection[str] = (), *, expected: str | None = None,
                got: str | None = None) -> Mapping[str, Any]:
        """``obj`` as a mapping: ``expected <expected or container>, got <its kind (or
        got)>``; with ``allowed``, no other key; every ``required`` key present."""
        if not isinstance(obj, Mapping):
            raise self.fail(where, f"expected {expected or self.container}, "
                                   f"got {kind_of(obj) if got is None else got}")
        if allowed is not None:
            unknown = unknown_keys(obj, allowed)
            if unknown:
                raise self.fail(where, unknown)
        missing = sorted(k for k in required if k not in obj)
        if missing:
            raise self.fail(where, f"missing required field(s) {', '.join(repr(k) for k in missing)}")
        return obj

    def items(self, obj: Any, where: str) -> list[Any]:
        """``obj`` as a list: ``<list_wording>, got <its kind>``."""
        if not isinstance(obj, list):
            raise self.fail(where, f"{self.list_wording}, got {kind_of(obj)}")
        return obj

    def number(self, obj: Any, where: str, *, positive: bool = False, nonneg: bool = False,
               limit: float = MAX_MAGNITUDE) -> float:
        """A finite number within ``limit`` (:func:`perfros_bag.limits.number_problem`)."""
        problem = number_problem(obj, positive=positive, nonneg=nonneg, limit=limit)
        if problem is not None:
            raise self.fail(where, problem)
        return float(obj)

    def opt_number(self, obj: Any, where: str, **kw: Any) -> float | None:
        """:meth:`number`, or None for a missing (null) one."""
        return None if obj is None else self.number(obj, where, **kw)

    def string(self, obj: Any, where: str) -> str:
        """Non-empty text."""
        if not isinstance(obj, str) or not obj.strip():
            raise self.fail(where, f"must be a non-empty string, got {obj!r}")
        return obj

    def enum(self, obj: Any, where: str, kind: type[E], *, wording: str | None = None) -> E:
        """One of ``kind``'s values: ``<wording>, got <obj>`` (default ``must be one of
        'a', 'b'``)."""
        try:
            return kind(obj)
        except ValueError:
            said = wording or f"must be one of {', '.join(repr(k.value) for k in kind)}"
            raise self.fail(where, f"{said}, got {obj!r}") from None
