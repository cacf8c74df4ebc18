"""model.json's ``system`` part, read without the rest of the document: what ``solve``
needs (a system.yaml with fitted curves). The whole document, its writer and its checked
reader are the fit's (:mod:`perfros_bag.fitting.modelfile`); this part sits below it, so
that the system's reader (:mod:`perfros_bag.system.systemfile`) never imports the fit."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from perfros_bag.fileio import DOCUMENT_KINDS, SYSTEM_KIND, expect_kind, read_json

#: model.json's ``format``
MODEL_FORMAT = "perfros-bag/model@1"


def system_part(data: Any) -> Any:
    """The ``system`` part of a parsed model.json; any other data unchanged (a system
    written as JSON)."""
    if isinstance(data, Mapping) and "system" in data:
        return data["system"]
    return data


def read_model_system(path: str | Path) -> Any:
    """What ``solve`` reads from a model.json: its ``system`` part, unchecked (the rest of
    the document is not needed to solve). Another of the tool's documents (a plan, ...) is
    an :class:`InputError` saying what it is."""
    data = read_json(path)
    expect_kind(path, data, "a system.yaml or model.json", {SYSTEM_KIND, DOCUMENT_KINDS[MODEL_FORMAT]})
    return system_part(data)
