"""Bounded JSON decoding and the schema check of imufdi_cli.jsonin."""

from __future__ import annotations

import json

import pytest

from imufdi_cli import jsonin
from imufdi_cli.errors import InputDataError, McapInputError
from imufdi_cli.jsonin import Int, Int64, ListOf, MapOf, Number, Obj, Optional, Str, check


@pytest.mark.parametrize(
    ("text", "depth"),
    [
        ('{"a": "' + "[" * 80 + '"}', 1),
        ('[{"a": "\\"]]]]"}, ' + "[" * 70 + "]" * 70 + "]", 71),
        ("[" * 100_000 + "]" * 100_000, 100_000),
    ],
)
def test_nesting_depth_counts_brackets_outside_strings(text, depth):
    assert jsonin.nesting_depth(text) == depth
    assert jsonin.nesting_depth(text.encode()) == depth


def test_a_document_with_few_brackets_is_not_scanned():
    """At most MAX_DEPTH brackets in all: their count bounds the depth (no scan)."""
    assert jsonin.nesting_depth("[[1], [2, [3]]]") == 4
    assert jsonin.nesting_depth("5") == 0


def test_deep_json_is_refused_before_the_recursive_decoder_runs():
    text = "[" * 100_000 + "]" * 100_000
    with pytest.raises(McapInputError, match="x: JSON nested 100000 levels deep; at most 64"):
        jsonin.loads(text, "x", McapInputError)
    ok = "[" * 64 + "]" * 64
    assert jsonin.loads(ok, "x") == json.loads(ok)


@pytest.mark.parametrize("text", ["{", b"\xff\xfe", "", "[1,]"])
def test_invalid_json_is_one_error_naming_the_document(text):
    with pytest.raises(InputDataError, match=r"^doc: not valid JSON \("):
        jsonin.loads(text, "doc")


SCHEMA = Obj(
    required={"t0_ns": Int64(), "faults": ListOf(Obj(required={"at_s": Number(limit=1e9)}))},
    optional={"window": Optional(ListOf(Number(), length=2)), "names": MapOf(Str())},
)


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (None, "doc: expected an object, got null"),
        ([], "doc: expected an object, got a list of 0"),
        ({"faults": []}, "doc: missing key 't0_ns'"),
        ({"t0_ns": True, "faults": []}, "doc: t0_ns: expected a 64-bit integer, got a boolean"),
        ({"t0_ns": 2**64, "faults": []}, "t0_ns: expected a 64-bit integer, got the integer"),
        ({"t0_ns": 1, "faults": [5]}, "doc: faults[0]: expected an object, got the integer 5"),
        (
            {"t0_ns": 1, "faults": [{"at_s": "x"}]},
            "doc: faults[0].at_s: expected a finite number of magnitude <= 1e+09, got the string",
        ),
        ({"t0_ns": 1, "faults": [{"at_s": float("nan")}]}, "faults[0].at_s: expected a finite"),
        ({"t0_ns": 1, "faults": [{"at_s": 10**400}]}, "faults[0].at_s: expected a finite"),
        ({"t0_ns": 1, "faults": [], "window": [1]}, "window: expected a list of 2 or null"),
        ({"t0_ns": 1, "faults": [], "window": [1, "a"]}, r"window[1]: expected a finite number"),
        ({"t0_ns": 1, "faults": [], "names": {"a": 1}}, "names.a: expected a string"),
    ],
)
def test_a_document_off_its_schema_names_the_first_bad_value(value, message):
    with pytest.raises(InputDataError) as info:
        check(value, SCHEMA, "doc")
    assert message in str(info.value)


def test_a_document_on_its_schema_passes_with_extra_keys():
    value = {"t0_ns": -5, "faults": [{"at_s": 1.5, "new": 1}], "window": None, "future": [1]}
    assert check(value, SCHEMA, "doc") is value
    with pytest.raises(InputDataError, match="doc: other: unknown key; valid: a"):
        check({"a": 1, "other": 2}, Obj(optional={"a": Int()}, closed=True), "doc")
