"""doccheck.Doc: each check's one-line message, written out here by hand (the readers'
own bad-input tests pin the messages of each format)."""

from __future__ import annotations

from collections.abc import Callable
from enum import Enum

import pytest

from perfros_bag.doccheck import Doc
from perfros_bag.errors import InputError


class Colour(Enum):
    RED = "red"
    BLUE = "blue"


class JsonDoc(Doc):
    container = "an object"
    list_wording = "expected a list"


def message(check: Callable[[], object]) -> str:
    with pytest.raises(InputError) as info:
        check()
    return str(info.value)


def test_each_check_names_the_file_and_the_place() -> None:
    doc = Doc("s.yaml")
    assert message(lambda: doc.mapping([1], "nodes[0]")) == "s.yaml: nodes[0]: expected a mapping, got list"
    assert message(lambda: doc.mapping({"b": 1, "a": 2}, "top", {"a"})) \
        == "s.yaml: top: unknown key(s) 'b' (allowed: a)"
    assert message(lambda: doc.mapping({}, "nodes[1]", {"name", "cpu"}, {"name", "cpu"})) \
        == "s.yaml: nodes[1]: missing required field(s) 'cpu', 'name'"
    assert message(lambda: doc.items({}, "edges")) == "s.yaml: edges: must be a list, got dict"
    assert message(lambda: doc.number("x", "cpu")) == "s.yaml: cpu: must be a finite number, got 'x'"
    assert message(lambda: doc.number(-1, "cpu", positive=True)) == "s.yaml: cpu: must be > 0, got -1"
    assert message(lambda: doc.string("  ", "name")) == "s.yaml: name: must be a non-empty string, got '  '"
    assert message(lambda: doc.enum("green", "colour", Colour)) \
        == "s.yaml: colour: must be one of 'red', 'blue', got 'green'"
    assert message(lambda: doc.enum(3, "colour", Colour, wording="must be red or blue")) \
        == "s.yaml: colour: must be red or blue, got 3"
    assert str(doc.fail("", "the file is empty")) == "s.yaml: the file is empty"


def test_values_that_pass_come_back_as_read() -> None:
    doc = Doc("s.yaml")
    data = {"a": 1}
    assert doc.mapping(data, "top", {"a"}, {"a"}) is data
    assert doc.number(3, "cpu") == 3.0 and isinstance(doc.number(3, "cpu"), float)
    assert doc.opt_number(None, "cpu") is None
    assert doc.enum("blue", "colour", Colour) is Colour.BLUE
    assert doc.items([], "edges") == []


def test_a_format_states_its_own_words() -> None:
    doc = JsonDoc("m.json")
    assert message(lambda: doc.mapping(None, "fits")) == "m.json: fits: expected an object, got nothing"
    assert message(lambda: doc.items(3, "measured")) == "m.json: measured: expected a list, got int"
    assert message(lambda: doc.mapping(None, "x", expected="a mapping with 'path:'", got="NoneType")) \
        == "m.json: x: expected a mapping with 'path:', got NoneType"
